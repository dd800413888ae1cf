"""Context encoders (paper, Context Encoding): grasp set and point cloud, queried by h0_d.

Both end in a transformer decoder whose single query is a projection of the past-dynamics
encoding ``h0_d``; cross-attention picks the grasps / scene regions relevant to the current
motion. Each memory always contains one learned "null" token, so a sample with no valid grasp
(or no point) gets a well-defined encoding: the decoder then attends only to that token
(documented fallback, no error).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from rtv3_maniskill.policies.rtv3.point_encoder import PointTransformerEncoder


def compact_valid_rows(tokens: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Drop padding from a set: ``tokens (B, M, F)``, ``valid (B, M)`` bool -> ``(B, M', F)``, ``(B, M')``.

    Each row's valid entries move to the front (in their order) and the columns no row needs
    are cut, ``M' = max_b sum valid[b]``. For an unordered, masked set (no positional encoding,
    padding masked as keys) the encodings are unchanged; attention simply skips the padding
    (a scene offers ~10 of the 64 grasp slots).
    """
    counts = valid.sum(1)
    width = int(counts.max()) if valid.numel() else 0
    if width == valid.shape[1]:
        return tokens, valid
    if bool((valid[:, :width].sum(1) == counts).all()):  # already packed at the front
        return tokens[:, :width], valid[:, :width]
    order = torch.argsort((~valid).to(torch.int8), dim=1, stable=True)[:, :width]
    return torch.gather(tokens, 1, order[..., None].expand(-1, -1, tokens.shape[-1])), torch.gather(valid, 1, order)


class QueryDecoderLayer(nn.Module):
    """Transformer decoder layer (post-norm, as ``nn.TransformerDecoderLayer``) for a single query token.

    With one query, self-attention over the query sequence reduces exactly to ``W_o (W_v x)``;
    writing it out saves most of the per-call overhead at inference.
    """

    def __init__(self, dim: int, heads: int, feedforward: int, dropout: float):
        super().__init__()
        self.heads = heads
        self.self_value = nn.Linear(dim, dim)
        self.self_out = nn.Linear(dim, dim)
        self.cross_query = nn.Linear(dim, dim)
        self.cross_key_value = nn.Linear(dim, 2 * dim)
        self.cross_out = nn.Linear(dim, dim)
        self.feedforward = nn.Sequential(
            nn.Linear(dim, feedforward), nn.ReLU(), nn.Dropout(dropout), nn.Linear(feedforward, dim)
        )
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(dim), nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.dropout = nn.Dropout(dropout)

    def forward(self, query: torch.Tensor, memory: torch.Tensor, attend: torch.Tensor) -> torch.Tensor:
        """``query (B, C)``, ``memory (B, L, C)``, ``attend (B, L)`` bool (True = real) -> ``(B, C)``."""
        b, length, dim = memory.shape
        h = self.heads
        x = self.norm1(query + self.dropout(self.self_out(self.self_value(query))))
        q = self.cross_query(x).view(b, h, 1, dim // h)
        kv = self.cross_key_value(memory).view(b, length, 2, h, dim // h).permute(2, 0, 3, 1, 4)
        attn = F.scaled_dot_product_attention(
            q, kv[0], kv[1], attn_mask=attend[:, None, None, :],
            dropout_p=self.dropout.p if self.training else 0.0,
        )
        x = self.norm2(x + self.dropout(self.cross_out(attn.reshape(b, dim))))
        return self.norm3(x + self.dropout(self.feedforward(x)))


class QueryDecoder(nn.Module):
    """``h = TransformerDecoder(memory, query = W h0_d)`` with a learned null memory token."""

    def __init__(self, query_dim: int, dim: int, heads: int, layers: int, feedforward: int, dropout: float):
        super().__init__()
        self.query = nn.Linear(query_dim, dim)
        self.null_token = nn.Parameter(torch.randn(1, 1, dim) * 0.02)
        self.layers = nn.ModuleList(QueryDecoderLayer(dim, heads, feedforward, dropout) for _ in range(layers))

    def forward(self, memory: torch.Tensor, valid: torch.Tensor, h_dynamics: torch.Tensor) -> torch.Tensor:
        """``memory (B, L, C)``, ``valid (B, L)`` bool, ``h_dynamics (B, Dq)`` -> ``(B, C)``."""
        batch = memory.shape[0]
        memory = torch.cat([self.null_token.expand(batch, -1, -1), memory], 1)
        attend = torch.cat([valid.new_ones(batch, 1), valid], 1)
        x = self.query(h_dynamics)
        for layer in self.layers:
            x = layer(x, memory, attend)
        return x


class GraspEncoder(nn.Module):
    """``f_grasp = TransformerEncoder(G)``; ``h_grasp = TransformerDecoder(f_grasp, h0_d)``.

    Grasps are an unordered set: no positional encoding; padding rows are masked. The encoder
    is pre-norm with a final LayerNorm: each grasp token keeps a residual path from its own
    embedding, so the tokens stay distinguishable (a post-norm encoder trained on planner data
    collapsed every token to one vector and the prior ignored its goal).
    """

    def __init__(self, in_dim: int, query_dim: int, dim: int, heads: int, encoder_layers: int,
                 decoder_layers: int, feedforward: int, dropout: float):
        super().__init__()
        self.embed = nn.Linear(in_dim, dim)
        layer = nn.TransformerEncoderLayer(dim, heads, feedforward, dropout, batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, encoder_layers, norm=nn.LayerNorm(dim), enable_nested_tensor=False)
        self.decoder = QueryDecoder(query_dim, dim, heads, decoder_layers, feedforward, dropout)
        self.out_dim = dim

    def forward(self, grasp_feat: torch.Tensor, valid: torch.Tensor, h_dynamics: torch.Tensor) -> torch.Tensor:
        """``grasp_feat (B, M, F)`` EE-frame grasp features, ``valid (B, M)`` -> ``h_grasp (B, dim)``."""
        grasp_feat, valid = compact_valid_rows(grasp_feat, valid)
        tokens = self.embed(grasp_feat)
        if tokens.shape[1] > 0 and self.training:
            tokens = self._encode_real_tokens(tokens, valid)
        elif tokens.shape[1] > 0:
            # A fully masked row would give NaN attention; such rows are ignored by the decoder anyway.
            any_valid = valid.any(1, keepdim=True)
            pad = ~valid & any_valid
            # No padding left (one sample, or equal counts): the unmasked kernel is faster, same result.
            tokens = self.encoder(tokens, src_key_padding_mask=pad if bool(pad.any()) else None)
        return self.decoder(tokens, valid, h_dynamics)


    def _encode_real_tokens(self, tokens: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """``self.encoder`` (pre-norm layers + final norm) computed on the real tokens only: norms, projections
        and feed-forward run on the packed real rows, attention on the padded layout with the padding masked.

        Training path: in a batch with grasp-subset augmentation most rows are padding (the width is the
        largest set). The real tokens get the same function as from ``self.encoder`` with
        ``src_key_padding_mask``; padded rows come back as zeros (the decoder never reads them)."""
        batch, width, dim = tokens.shape
        rows = valid.reshape(-1).nonzero().squeeze(1)
        x = tokens.reshape(batch * width, dim).index_select(0, rows)
        # a sample without real grasps attends over its (zero) rows instead of nothing (no NaN anywhere)
        attend = (valid | ~valid.any(1, keepdim=True))[:, None, None, :]
        for layer in self.encoder.layers:
            attn = layer.self_attn
            heads = attn.num_heads
            qkv = F.linear(layer.norm1(x), attn.in_proj_weight, attn.in_proj_bias)
            qkv = qkv.new_zeros(batch * width, 3 * dim).index_copy(0, rows, qkv)
            qkv = qkv.view(batch, width, 3, heads, dim // heads).permute(2, 0, 3, 1, 4)
            out = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2], attn_mask=attend,
                                                 dropout_p=attn.dropout if self.training else 0.0)
            out = out.transpose(1, 2).reshape(batch * width, dim).index_select(0, rows)
            x = x + layer.dropout1(attn.out_proj(out))
            x = x + layer.dropout2(layer.linear2(layer.dropout(layer.activation(layer.linear1(layer.norm2(x))))))
        if self.encoder.norm is not None:
            x = self.encoder.norm(x)
        return tokens.new_zeros(batch * width, dim).index_copy(0, rows, x).view(batch, width, dim)


class PointCloudEncoder(nn.Module):
    """``f_pcl = PTv3(P)``; ``h_pcl = TransformerDecoder(f_pcl, h0_d)`` (1 layer, 4 heads)."""

    def __init__(self, in_dim: int, query_dim: int, channels: tuple[int, ...], heads: tuple[int, ...],
                 depths: tuple[int, ...], patch_size: int, grid_size: float, position_scale: float,
                 decoder_heads: int, decoder_layers: int, dropout: float, stem_poolings: int = 0):
        super().__init__()
        self.backbone = PointTransformerEncoder(in_dim, channels, heads, depths, patch_size, grid_size, position_scale,
                                                stem_poolings)
        dim = self.backbone.out_dim
        self.decoder = QueryDecoder(query_dim, dim, decoder_heads, decoder_layers, 4 * dim, dropout)
        self.out_dim = dim

    def forward(self, xyz: torch.Tensor, feat: torch.Tensor, valid: torch.Tensor,
                h_dynamics: torch.Tensor) -> torch.Tensor:
        """``xyz (B, N, 3)`` EE frame (m), ``feat (B, N, F)``, ``valid (B, N)`` -> ``h_pcl (B, C)``."""
        tokens, token_valid = self.backbone(xyz, feat, valid)
        return self.decoder(tokens, token_valid, h_dynamics)
