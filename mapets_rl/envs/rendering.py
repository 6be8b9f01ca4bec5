"""Video frames of the traffic scenarios that say who is who.

highway-env draws every IDM vehicle the same blue and removes a crashed vehicle from the road at
the end of its crash step, so in a video CAVs and human drivers look alike and crashes vanish.
The helpers here, used by a scenario's ``render`` when it has a ``render_mode``:

- :func:`paint_vehicles`: CAVs in :data:`CAV_COLOR` (green), human drivers in :data:`HV_COLOR`
  (blue), through highway-env's per-vehicle ``color`` attribute;
- :class:`CrashSites`: where and when vehicles crashed (recorded before they leave the road);
  :func:`decorate_frame` marks each site with a red box and cross (:data:`CRASH_COLOR`) for the
  rest of the episode, and draws a legend (CAV / human driver / crash site, with counts) in the
  top-left corner;
- :func:`draw_step_counter`: ``step k / H`` in the top-right corner, drawn by
  ``MultiAgentTrafficEnv.render`` for every scenario.

Both scenarios use them: the figure-eight (whole track in view) and the freeway.
The camera is the scenario's business (the freeway centres on the mean position of the CAVs
still driving, ``FreewayEnv.view_centre``; the freeway with an on-ramp stays on the merge
area, ``FreewayMergeEnv.view_centre``, on both backends).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

CAV_COLOR = (50, 200, 0)
"""Fill colour of a CAV (RGB)."""
HV_COLOR = (100, 200, 255)
"""Fill colour of a human-driven vehicle (RGB)."""
CRASH_COLOR = (230, 20, 20)
"""Colour of a crash-site marker (RGB)."""
LEGEND_BACKGROUND = (255, 255, 255)
LEGEND_TEXT = (20, 20, 20)
LEGEND_ORIGIN = (6, 6)
"""Top-left pixel of the legend box."""
SWATCH = 10
"""Side of a legend colour swatch [pixels]."""
STEP_COUNTER_MARGIN = 6
"""Distance of the step counter's box from the top and right edges [pixels]."""


@dataclass
class CrashSites:
    """Vehicles that crashed this episode: position ``[x, y]`` (m), heading (rad), length and
    width (m), whether it was a CAV. Cleared at reset."""

    positions: list[np.ndarray] = field(default_factory=list)
    headings: list[float] = field(default_factory=list)
    sizes: list[tuple[float, float]] = field(default_factory=list)
    is_cav: list[bool] = field(default_factory=list)
    _seen: set[int] = field(default_factory=set)

    def clear(self) -> None:
        self.positions.clear()
        self.headings.clear()
        self.sizes.clear()
        self.is_cav.clear()
        self._seen.clear()

    def record(self, vehicles: list[Any], cav_ids: set[int]) -> None:
        """Remember every crashed vehicle of ``vehicles`` not recorded yet (``cav_ids``: the
        ``id`` of the CAVs)."""
        for vehicle in vehicles:
            if vehicle.crashed and id(vehicle) not in self._seen:
                self._seen.add(id(vehicle))
                self.positions.append(np.array(vehicle.position, dtype=float))
                self.headings.append(float(vehicle.heading))
                self.sizes.append((float(vehicle.LENGTH), float(vehicle.WIDTH)))
                self.is_cav.append(id(vehicle) in cav_ids)

    def __len__(self) -> int:
        return len(self.positions)


def paint_vehicles(vehicles: list[Any], cav_ids: set[int]) -> None:
    """Give every vehicle its colour: :data:`CAV_COLOR` for the CAVs, :data:`HV_COLOR` else."""
    for vehicle in vehicles:
        vehicle.color = CAV_COLOR if id(vehicle) in cav_ids else HV_COLOR


def decorate_frame(
    frame: np.ndarray, surface: Any, crashes: CrashSites, counts: dict[str, int]
) -> np.ndarray:
    """``frame`` ``[H, W, 3]`` with the crash sites marked and the legend drawn.

    Args:
        frame: the viewer's RGB image (height x width x 3, uint8).
        surface: the viewer's ``WorldSurface`` that drew ``frame`` (its ``pos2pix`` and
            ``pix`` map metres to pixels).
        crashes: the crash sites to mark.
        counts: ``{"CAVs": n, "human drivers": m}`` still on the road, shown in the legend.

    Returns:
        A new ``[H, W, 3]`` uint8 array.
    """
    import pygame

    if not pygame.font.get_init():
        pygame.font.init()
    image = pygame.surfarray.make_surface(np.ascontiguousarray(np.swapaxes(frame, 0, 1)))
    for position, heading, (length, width) in zip(
        crashes.positions, crashes.headings, crashes.sizes, strict=True
    ):
        _mark_crash(image, surface, position, heading, length, width)
    _legend(image, counts, len(crashes))
    return np.ascontiguousarray(np.swapaxes(pygame.surfarray.array3d(image), 0, 1))


def _mark_crash(
    image: Any, surface: Any, position: np.ndarray, heading: float, length: float, width: float
) -> None:
    """A red outline of the vehicle's footprint with a cross through it."""
    import pygame

    c, s = np.cos(heading), np.sin(heading)
    half = np.array([[length, width], [length, -width], [-length, -width], [-length, width]]) / 2
    corners = position + half @ np.array([[c, s], [-s, c]])
    pixels = [surface.pos2pix(x, y) for x, y in corners]
    thickness = max(2, surface.pix(0.4))
    pygame.draw.polygon(image, CRASH_COLOR, pixels, thickness)
    pygame.draw.line(image, CRASH_COLOR, pixels[0], pixels[2], thickness)
    pygame.draw.line(image, CRASH_COLOR, pixels[1], pixels[3], thickness)


def _legend(image: Any, counts: dict[str, int], crashes: int) -> None:
    """Legend box in the top-left corner: a swatch and a label per kind of mark."""
    import pygame

    font = pygame.font.Font(None, 16)
    entries = [
        (CAV_COLOR, f"CAV ({counts.get('CAVs', 0)})"),
        (HV_COLOR, f"human driver ({counts.get('human drivers', 0)})"),
        (CRASH_COLOR, f"crash site ({crashes})"),
    ]
    labels = [font.render(text, True, LEGEND_TEXT) for _, text in entries]
    row = SWATCH + 4
    width = SWATCH + 10 + max(label.get_width() for label in labels)
    x0, y0 = LEGEND_ORIGIN
    pygame.draw.rect(image, LEGEND_BACKGROUND, (x0, y0, width + 4, row * len(entries) + 4))
    for k, ((color, _), label) in enumerate(zip(entries, labels, strict=True)):
        y = y0 + 4 + k * row
        pygame.draw.rect(image, color, (x0 + 4, y, SWATCH, SWATCH))
        image.blit(label, (x0 + SWATCH + 8, y - 1))


def draw_step_counter(frame: np.ndarray, step: int, horizon: int) -> np.ndarray:
    """``frame`` ``[H, W, 3]`` with ``step k / H`` (dark text on a white box) in its top-right
    corner, :data:`STEP_COUNTER_MARGIN` pixels from the edges; a new uint8 array."""
    import pygame

    if not pygame.font.get_init():
        pygame.font.init()
    image = pygame.surfarray.make_surface(np.ascontiguousarray(np.swapaxes(frame, 0, 1)))
    label = pygame.font.Font(None, 18).render(f"step {step} / {horizon}", True, LEGEND_TEXT)
    width, height = label.get_width() + 8, label.get_height() + 6
    x0 = image.get_width() - STEP_COUNTER_MARGIN - width
    pygame.draw.rect(image, LEGEND_BACKGROUND, (x0, STEP_COUNTER_MARGIN, width, height))
    image.blit(label, (x0 + 4, STEP_COUNTER_MARGIN + 3))
    return np.ascontiguousarray(np.swapaxes(pygame.surfarray.array3d(image), 0, 1))
