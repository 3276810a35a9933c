"""CircleNet's training loss (CenterNet's, with the radius as the only size).

- Centre heat map: the penalty-reduced pixel-wise focal loss of CornerNet/CenterNet on
  Gaussian targets (alpha = 2, beta = 4), summed and divided by the number of objects.
- Offset and radius: L1 at the objects' centre cells only, averaged over the objects.
The total is heat + offset_weight * offset + radius_weight * radius, averaged over the stacks
(intermediate supervision of the hourglass; the ResNet has one).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def focal_loss(logits: torch.Tensor, target: torch.Tensor, alpha: float = 2.0, beta: float = 4.0) -> torch.Tensor:
    """Penalty-reduced focal loss.

    logits: (B, 1, h, w) heat-map logits. target: (B, 1, h, w) in [0, 1], exactly 1 at object
    centres, a Gaussian around them. Returns a scalar: the sum over cells / max(1, #centres).
    log p and log(1 - p) come from logsigmoid, stable where CenterNet clamps p to [1e-4, 1 - 1e-4].
    """
    logits, target = logits.float(), target.float()
    p = torch.sigmoid(logits)
    pos = target.eq(1).float()
    pos_loss = -((1 - p) ** alpha) * F.logsigmoid(logits) * pos
    neg_loss = -((1 - target) ** beta) * (p ** alpha) * F.logsigmoid(-logits) * (1 - pos)
    return (pos_loss.sum() + neg_loss.sum()) / pos.sum().clamp(min=1.0)


def gather_cells(maps: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """Values of maps (B, C, h, w) at flat cell indices (B, M) -> (B, M, C)."""
    b, c = maps.shape[:2]
    return maps.reshape(b, c, -1).gather(2, cells[:, None, :].expand(-1, c, -1)).transpose(1, 2)


def masked_l1(pred: torch.Tensor, cells: torch.Tensor, mask: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L1 at the object cells: pred (B, C, h, w), cells (B, M) flat cells, mask (B, M) 1 for a
    real object, target (B, M, C). Returns a scalar: the mean over real objects and channels."""
    diff = (gather_cells(pred.float(), cells) - target.float()).abs() * mask[..., None]
    return diff.sum() / (mask.sum() * pred.shape[1] + 1e-4)


def circlenet_loss(stages: list[dict[str, torch.Tensor]], targets: dict[str, torch.Tensor],
                   offset_weight: float = 1.0, radius_weight: float = 0.1) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss over the stacks, and its parts (floats, for the progress bar).

    stages: per stack {"heat": (B, 1, h, w) logits, "offset": (B, 2, h, w), "radius": (B, 1, h, w)}.
    targets: {"heat": (B, 1, h, w), "cells": (B, M) int64, "mask": (B, M), "offset": (B, M, 2),
    "radius": (B, M, 1)} as rendered by ``data.render_targets`` (grid units).
    radius_weight 0.1 is CenterNet's size weight.
    """
    parts = {"heat": 0.0, "offset": 0.0, "radius": 0.0}
    total = 0.0
    for out in stages:
        heat = focal_loss(out["heat"], targets["heat"])
        off = masked_l1(out["offset"], targets["cells"], targets["mask"], targets["offset"])
        rad = masked_l1(out["radius"], targets["cells"], targets["mask"], targets["radius"])
        total = total + heat + offset_weight * off + radius_weight * rad
        for k, v in (("heat", heat), ("offset", off), ("radius", rad)):
            parts[k] += float(v.detach()) / len(stages)
    total = total / len(stages)
    parts["total"] = float(total.detach())
    return total, parts
