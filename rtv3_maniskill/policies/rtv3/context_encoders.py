"""Context encoders (paper, Context Encoding): grasp set and point cloud, queried by h0_d.

Both end in a transformer decoder whose single query is a projection of the past-dynamics
encoding ``h0_d``; cross-attention picks the grasps / scene regions relevant to the current
motion. Each memory always contains one learned "null" token, so a sample with no valid grasp
(or no point) gets a well-defined encoding: the decoder then attends only to that token
(documented fallback, no error).
"""

from __future__ import annotations

import torch
from torch import nn

from rtv3_maniskill.policies.rtv3.point_encoder import PointTransformerEncoder


class QueryDecoder(nn.Module):
    """``h = TransformerDecoder(memory, query = W h0_d)`` with a learned null memory token."""

    def __init__(self, query_dim: int, dim: int, heads: int, layers: int, feedforward: int, dropout: float):
        super().__init__()
        self.query = nn.Linear(query_dim, dim)
        self.null_token = nn.Parameter(torch.randn(1, 1, dim) * 0.02)
        layer = nn.TransformerDecoderLayer(dim, heads, feedforward, dropout, batch_first=True)
        self.decoder = nn.TransformerDecoder(layer, layers)

    def forward(self, memory: torch.Tensor, valid: torch.Tensor, h_dynamics: torch.Tensor) -> torch.Tensor:
        """``memory (B, L, C)``, ``valid (B, L)`` bool, ``h_dynamics (B, Dq)`` -> ``(B, C)``."""
        batch = memory.shape[0]
        memory = torch.cat([self.null_token.expand(batch, -1, -1), memory], 1)
        ignore = torch.cat([valid.new_zeros(batch, 1), ~valid], 1)
        query = self.query(h_dynamics)[:, None]
        return self.decoder(query, memory, memory_key_padding_mask=ignore)[:, 0]


class GraspEncoder(nn.Module):
    """``f_grasp = TransformerEncoder(G)``; ``h_grasp = TransformerDecoder(f_grasp, h0_d)``.

    Grasps are an unordered set: no positional encoding; padding rows are masked.
    """

    def __init__(self, in_dim: int, query_dim: int, dim: int, heads: int, encoder_layers: int,
                 decoder_layers: int, feedforward: int, dropout: float):
        super().__init__()
        self.embed = nn.Linear(in_dim, dim)
        layer = nn.TransformerEncoderLayer(dim, heads, feedforward, dropout, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, encoder_layers, enable_nested_tensor=False)
        self.decoder = QueryDecoder(query_dim, dim, heads, decoder_layers, feedforward, dropout)
        self.out_dim = dim

    def forward(self, grasp_feat: torch.Tensor, valid: torch.Tensor, h_dynamics: torch.Tensor) -> torch.Tensor:
        """``grasp_feat (B, M, F)`` EE-frame grasp features, ``valid (B, M)`` -> ``h_grasp (B, dim)``."""
        tokens = self.embed(grasp_feat)
        if tokens.shape[1] > 0:
            # A fully masked row would give NaN attention; such rows are ignored by the decoder anyway.
            any_valid = valid.any(1, keepdim=True)
            pad = ~valid & any_valid
            tokens = self.encoder(tokens, src_key_padding_mask=pad)
        return self.decoder(tokens, valid, h_dynamics)


class PointCloudEncoder(nn.Module):
    """``f_pcl = PTv3(P)``; ``h_pcl = TransformerDecoder(f_pcl, h0_d)`` (1 layer, 4 heads)."""

    def __init__(self, in_dim: int, query_dim: int, channels: tuple[int, ...], heads: tuple[int, ...],
                 depths: tuple[int, ...], patch_size: int, grid_size: float, position_scale: float,
                 decoder_heads: int, decoder_layers: int, dropout: float):
        super().__init__()
        self.backbone = PointTransformerEncoder(in_dim, channels, heads, depths, patch_size, grid_size, position_scale)
        dim = self.backbone.out_dim
        self.decoder = QueryDecoder(query_dim, dim, decoder_heads, decoder_layers, 4 * dim, dropout)
        self.out_dim = dim

    def forward(self, xyz: torch.Tensor, feat: torch.Tensor, valid: torch.Tensor, h_dynamics: torch.Tensor) -> torch.Tensor:
        """``xyz (B, N, 3)`` EE frame (m), ``feat (B, N, F)``, ``valid (B, N)`` -> ``h_pcl (B, C)``."""
        tokens, token_valid = self.backbone(xyz, feat, valid)
        return self.decoder(tokens, token_valid, h_dynamics)
