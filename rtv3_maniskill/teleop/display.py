"""The ``rtv3 teleop`` window (pygame): the rendered scene and a side panel with the session's state.

The panel shows the method, the assistance mode (coloured), the task text, the grasp phase and
gripper, elapsed time, contacts, the achieved control and display rates, the class weights (RT-V3:
top classes and entropy bounds; HO: the goal belief) and the key layout. Over the scene: a ring
on the target object and, for RT-V3, the grasp candidates the prior aims at (pre-grasp to grasp,
drawn as thick as the belief in them). Without a display set ``SDL_VIDEODRIVER=dummy``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

MODE_COLORS = {"starting": (200, 200, 200), "shared": (60, 200, 90), "autonomous": (80, 150, 255),
               "user_only": (230, 80, 70), "scripted": (240, 200, 40), "none": (160, 160, 160)}
PANEL_WIDTH = 380
KEY_HELP = ("move: w/s x  a/d y  q/e z (world axes)", "rotate: i/k  j/l  u/o", "f approach (Y)  g grasp (A)",
            "t lift (X)  r release (B)", "F12 screenshot  Esc quit")
WINDOW_TITLE = "RT-V3 teleop"


class TeleopDisplay:
    """A pygame window ``(scene width + PANEL_WIDTH) x scene height``."""

    def __init__(self, scene_size: tuple[int, int] = (512, 512)) -> None:
        import os

        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        import pygame

        pygame.display.init()
        pygame.font.init()
        self.pygame = pygame
        self.scene_size = scene_size
        self.screen = pygame.display.set_mode((scene_size[0] + PANEL_WIDTH, scene_size[1]))
        pygame.display.set_caption(WINDOW_TITLE)
        self.font = pygame.font.Font(None, 22)
        self.big = pygame.font.Font(None, 34)

    def events(self) -> list:
        """Pending pygame events (key presses, window close)."""
        return self.pygame.event.get()

    def _text(self, text: str, pos: tuple[int, int], color=(235, 235, 235), big: bool = False) -> None:
        self.screen.blit((self.big if big else self.font).render(text, True, color), pos)

    def draw(self, frame: np.ndarray | None, state: dict[str, Any], overlay: dict[str, Any] | None = None) -> None:
        """Show ``frame (H, W, 3)`` uint8 (None keeps the last one) and the panel from ``state``
        (method, mode, task, phase, gripper, time, timeout, contacts, trial, rates, diagnostics).
        ``overlay`` (pixels of ``frame``): ``target (2,)``, the target object's centre; ``grasps``: rows
        ``(u0, v0, u1, v1, weight)``, pre-grasp to grasp of the candidates the prior aims at."""
        pg = self.pygame
        w, h = self.scene_size
        if frame is not None:
            surface = pg.surfarray.make_surface(np.ascontiguousarray(np.asarray(frame)[..., :3].swapaxes(0, 1)))
            scale = (w / surface.get_width(), h / surface.get_height())
            if surface.get_size() != (w, h):
                surface = pg.transform.smoothscale(surface, (w, h))
            self.screen.blit(surface, (0, 0))
            self._overlay(overlay or {}, scale)
        pg.draw.rect(self.screen, (25, 25, 30), (w, 0, PANEL_WIDTH, h))
        x, y = w + 12, 10
        mode = state.get("mode") or "none"
        self._text(f"{state.get('method', '')}   trial {state.get('trial', '')}", (x, y))
        y += 26
        self._text(mode.replace("_", "-").upper(), (x, y), MODE_COLORS.get(mode, (200, 200, 200)), big=True)
        y += 34
        self._text(state.get("task", ""), (x, y), (255, 230, 150))
        y += 24
        self._text(f"phase: {state.get('phase', '')}   gripper: {state.get('gripper', '')}", (x, y))
        y += 22
        self._text(f"time: {state.get('time', 0.0):5.1f} s / {state.get('timeout', 0.0):.0f} s   "
                   f"contacts: {state.get('contacts', 0)}", (x, y))
        y += 22
        self._text(f"input: {state.get('input', '')}", (x, y))
        y += 22
        self._text(f"control {state.get('control_hz', 0.0):4.1f} Hz   display {state.get('display_hz', 0.0):4.1f} Hz",
                   (x, y), (150, 220, 150))
        y += 30
        y = self._weights(state.get("diagnostics", {}), x, y)
        for line in KEY_HELP:
            self._text(line, (x, h - 22 * (len(KEY_HELP) - KEY_HELP.index(line)) - 6), (170, 170, 180))
        if state.get("outcome"):
            self._text(f"trial over: {state['outcome']}", (12, 12), (255, 255, 255), big=True)
        pg.display.flip()

    def _overlay(self, overlay: dict[str, Any], scale: tuple[float, float]) -> None:
        pg = self.pygame
        sx, sy = scale
        for u0, v0, u1, v1, weight in overlay.get("grasps", ()):
            width = max(1, int(round(1 + 5 * float(weight))))
            pg.draw.line(self.screen, (255, 210, 40), (u0 * sx, v0 * sy), (u1 * sx, v1 * sy), width)
            pg.draw.circle(self.screen, (255, 210, 40), (u1 * sx, v1 * sy), width + 1)
        if overlay.get("target") is not None:
            u, v = overlay["target"]
            pg.draw.circle(self.screen, (255, 60, 200), (u * sx, v * sy), 16, 3)

    def _weights(self, diagnostics: dict[str, Any], x: int, y: int) -> int:
        weights = diagnostics.get("class_weights", diagnostics.get("belief"))
        if weights is None:
            self._text("no assistance (direct)", (x, y), (170, 170, 180))
            return y + 24
        weights = np.asarray(weights, dtype=float).reshape(-1)
        label = "class weights" if "class_weights" in diagnostics else "goal belief (HO)"
        self._text(f"{label} (top 5 of {len(weights)})", (x, y))
        y += 22
        for k in np.argsort(-weights)[:5]:
            self.pygame.draw.rect(self.screen, (90, 160, 240), (x + 70, y + 3, int(260 * weights[k]), 12))
            self._text(f"{int(k):3d}  {weights[k]:.2f}", (x, y))
            y += 18
        if "shown_grasps" in diagnostics:  # RT-V3's belief over the grasp candidates
            shown = [int(i) for i in diagnostics["shown_grasps"]]
            listed = ", ".join(map(str, shown[:6])) + (" ..." if len(shown) > 6 else "")
            self._text(f"prior aims at {len(shown)} of {diagnostics['grasp_candidates']} grasps: {listed}", (x, y + 4))
            y += 22
        if "trans_entropy_upper" in diagnostics:
            y += 4
            self._text(f"entropy trans {diagnostics['trans_entropy_upper']:.2f}  "
                       f"rot {diagnostics['rot_entropy_upper']:.2f}", (x, y))
            y += 22
        return y + 8

    def screenshot(self, path: str | Path) -> Path:
        """Save the window as a PNG; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.pygame.image.save(self.screen, str(path))
        return path

    def close(self) -> None:
        self.pygame.display.quit()


__all__ = ["KEY_HELP", "MODE_COLORS", "TeleopDisplay", "WINDOW_TITLE"]
