"""CircleNet: CenterNet with a circle representation (Yang et al., MICCAI 2020), in one file.

    image (B, 3, Hp, Wp), RGB in [0, 255], padded to multiples of 32 (``imaging.py``)
      -> normalisation (inside the network, so ONNX and PyTorch take the same array)
      -> backbone: features (B, C, Hp/4, Wp/4), stride 4
           "resnet18":  ResNet-18-style encoder (BasicBlocks 2-2-2-2, stride 32) and an FPN-style
                        upsampling neck back to stride 4: light, trainable on a CPU;
           "hourglass": a small stacked hourglass like CircleNet-HG (the paper's row), with
                        intermediate supervision: one set of heads per stack
      -> heads, each conv3x3-ReLU-conv1x1:
           heat   (B, 1, h, w)  centre heat map (logits; sigmoid -> probability)
           offset (B, 2, h, w)  sub-cell centre offset (dx, dy), grid units
           radius (B, 1, h, w)  circle radius, grid units (pixels / 4)
      -> decode: 3x3 max-pool peaks, top K, circles (cx, cy, r) px with scores.

Built from torch.nn alone and trained from scratch (no pretrained weights can be had here).
The head initialisation is CenterNet's: the heat-map bias -2.19 (a prior probability of 0.1), so
the focal loss starts small; regression heads start near zero.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from spherebench.baselines.circlenet.imaging import STRIDE, input_size
from spherebench.errors import SphereBenchError

BACKBONES = ("resnet18", "hourglass")


@dataclass
class CircleNetConfig:
    """Every default of the model in one place."""

    backbone: str = "resnet18"
    #: (height, width) px of the images the model takes: the benchmark's 424x240 D435 frames.
    image_size: tuple[int, int] = (240, 424)
    # -- input normalisation (RGB, applied inside the network) --
    pixel_mean: tuple[float, float, float] = (127.5, 127.5, 127.5)
    pixel_std: tuple[float, float, float] = (64.0, 64.0, 64.0)
    # -- "resnet18": stage widths width * (1, 2, 4, 8); 32 = half of ResNet-18's 64, which keeps
    # the ONNX file ~11 MB and CPU training 3-4x cheaper (64: `make train-full`, on a GPU) --
    resnet_width: int = 32
    resnet_blocks: tuple[int, int, int, int] = (2, 2, 2, 2)
    neck_channels: int = 64
    # -- "hourglass": widths at strides 4, 8, 16, 32 (three down-samplings, CenterNet's module) --
    hourglass_stacks: int = 2
    hourglass_stem: int = 64
    hourglass_channels: tuple[int, ...] = (64, 96, 128, 160)
    # -- heads --
    head_channels: int = 64
    heat_prior: float = 0.1  # initial centre probability: bias = -log((1 - p) / p) = -2.19
    # -- decoding --
    top_k: int = 100

    def __post_init__(self) -> None:
        if self.backbone not in BACKBONES:
            raise SphereBenchError(f"unknown backbone {self.backbone!r}; choose one of {', '.join(BACKBONES)}")
        self.image_size = tuple(int(s) for s in self.image_size)
        if len(self.image_size) != 2 or min(self.image_size) < 8:
            raise SphereBenchError(f"image_size must be (height, width) of at least 8 px, got {self.image_size}")

    @property
    def input_size(self) -> tuple[int, int]:
        """Network input (Hp, Wp) px: image_size padded to multiples of 32."""
        return input_size(self.image_size)

    @property
    def grid_size(self) -> tuple[int, int]:
        """Head output (h, w) cells: input_size / 4."""
        return tuple(s // STRIDE for s in self.input_size)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "CircleNetConfig":
        known = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**known)


# ---------------------------------------------------------------- building blocks

def conv_bn_relu(cin: int, cout: int, k: int = 3, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class BasicBlock(nn.Module):
    """ResNet basic block (also CenterNet-HG's 'residual'): x (B, cin, H, W) -> (B, cout, H/s, W/s)."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.skip = (nn.Identity() if stride == 1 and cin == cout else
                     nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        return F.relu(self.bn2(self.conv2(y)) + self.skip(x), inplace=True)


def upsample2(x: torch.Tensor) -> torch.Tensor:
    """Nearest-neighbour x2 up-sampling (B, C, H, W) -> (B, C, 2H, 2W); exact in ONNX Runtime too."""
    return F.interpolate(x, scale_factor=2.0, mode="nearest")


# ---------------------------------------------------------------- backbones

class ResNetFPN(nn.Module):
    """ResNet-18-style encoder + FPN-style neck: image (B, 3, Hp, Wp) -> [features (B, neck, Hp/4, Wp/4)].

    CenterNet's ResNet up-samples the stride-32 map with three deconvolutions; here the neck
    also adds 1x1 lateral connections from strides 16, 8 and 4, which trains faster from scratch.
    """

    def __init__(self, cfg: CircleNetConfig):
        super().__init__()
        w = cfg.resnet_width
        widths = [w, 2 * w, 4 * w, 8 * w]
        self.stem = nn.Sequential(conv_bn_relu(3, w, 7, 2), nn.MaxPool2d(3, 2, 1))  # stride 4
        stages, cin = [], w
        for i, (cout, n) in enumerate(zip(widths, cfg.resnet_blocks)):
            blocks = [BasicBlock(cin, cout, 1 if i == 0 else 2)] + [BasicBlock(cout, cout) for _ in range(n - 1)]
            stages.append(nn.Sequential(*blocks))
            cin = cout
        self.stages = nn.ModuleList(stages)  # strides 4, 8, 16, 32
        n = cfg.neck_channels
        self.lateral = nn.ModuleList(nn.Conv2d(c, n, 1) for c in widths)
        self.smooth = nn.ModuleList(conv_bn_relu(n, n) for _ in widths[:-1])
        self.out_channels = n

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        feats = []
        x = self.stem(x)
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        y = self.lateral[3](feats[3])
        for i in (2, 1, 0):  # top-down: stride 32 -> 16 -> 8 -> 4
            y = self.smooth[i](upsample2(y) + self.lateral[i](feats[i]))
        return [y]


class Hourglass(nn.Module):
    """One recursive hourglass level (CenterNet's kp_module): x (B, c0, H, W) -> (B, c0, H, W).

    channels: widths from this level down, e.g. (96, 128, 160, 192) = three down-samplings.
    """

    def __init__(self, channels: tuple[int, ...]):
        super().__init__()
        c, c_low = channels[0], channels[1]
        self.skip = BasicBlock(c, c)
        self.down = BasicBlock(c, c_low, stride=2)
        self.inner = Hourglass(channels[1:]) if len(channels) > 2 else BasicBlock(c_low, c_low)
        self.up = BasicBlock(c_low, c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.skip(x) + upsample2(self.up(self.inner(self.down(x))))


class StackedHourglass(nn.Module):
    """Small CircleNet-HG: image (B, 3, Hp, Wp) -> one feature map (B, c0, Hp/4, Wp/4) per stack."""

    def __init__(self, cfg: CircleNetConfig):
        super().__init__()
        c = cfg.hourglass_channels[0]
        self.stem = nn.Sequential(conv_bn_relu(3, cfg.hourglass_stem, 7, 2), BasicBlock(cfg.hourglass_stem, c, 2))
        s = cfg.hourglass_stacks
        self.hourglasses = nn.ModuleList(Hourglass(cfg.hourglass_channels) for _ in range(s))
        self.post = nn.ModuleList(conv_bn_relu(c, c) for _ in range(s))
        # between stacks (CenterNet): next input = relu(bn(1x1(input)) + bn(1x1(features))), then a block
        self.inter_in = nn.ModuleList(nn.Sequential(nn.Conv2d(c, c, 1, bias=False), nn.BatchNorm2d(c)) for _ in range(s - 1))
        self.inter_feat = nn.ModuleList(nn.Sequential(nn.Conv2d(c, c, 1, bias=False), nn.BatchNorm2d(c)) for _ in range(s - 1))
        self.inter_block = nn.ModuleList(BasicBlock(c, c) for _ in range(s - 1))
        self.out_channels = c

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = self.stem(x)
        feats = []
        for i, (hg, post) in enumerate(zip(self.hourglasses, self.post)):
            y = post(hg(x))
            feats.append(y)
            if i < len(self.hourglasses) - 1:
                x = self.inter_block[i](F.relu(self.inter_in[i](x) + self.inter_feat[i](y)))
        return feats


# ---------------------------------------------------------------- the detector

HEADS = {"heat": 1, "offset": 2, "radius": 1}


class Heads(nn.Module):
    """features (B, C, h, w) -> {"heat": (B, 1, h, w) logits, "offset": (B, 2, h, w), "radius": (B, 1, h, w)}."""

    def __init__(self, cin: int, cfg: CircleNetConfig):
        super().__init__()
        self.heads = nn.ModuleDict({
            name: nn.Sequential(nn.Conv2d(cin, cfg.head_channels, 3, 1, 1), nn.ReLU(inplace=True),
                                nn.Conv2d(cfg.head_channels, n, 1))
            for name, n in HEADS.items()})
        for name, head in self.heads.items():
            last = head[-1]
            if name == "heat":
                nn.init.constant_(last.bias, -math.log((1 - cfg.heat_prior) / cfg.heat_prior))
            else:  # CenterNet's fill_fc_weights: small weights, zero bias
                nn.init.normal_(last.weight, std=0.001)
                nn.init.zeros_(last.bias)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        out = {}
        for name, head in self.heads.items():
            hidden = head[1](head[0](x))
            # the last 1x1 conv in float32 even under mixed-precision training: bfloat16's 8-bit
            # mantissa is too coarse for radii of tens of grid units (a no-op in float32)
            with torch.autocast(x.device.type, enabled=False):
                out[name] = head[2](hidden.float())
        return out


class CircleNet(nn.Module):
    """The detector: image (B, 3, Hp, Wp) float RGB [0, 255] -> heads at stride 4.

    forward() is the graph that is exported: (heat probability, offset, radius), last stack only.
    forward_stages() gives the logits of every stack, for the loss (intermediate supervision).
    """

    def __init__(self, config: CircleNetConfig | None = None):
        super().__init__()
        self.config = cfg = config or CircleNetConfig()
        self.register_buffer("mean", torch.tensor(cfg.pixel_mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(cfg.pixel_std, dtype=torch.float32).view(1, 3, 1, 1))
        self.backbone = ResNetFPN(cfg) if cfg.backbone == "resnet18" else StackedHourglass(cfg)
        n_stages = cfg.hourglass_stacks if cfg.backbone == "hourglass" else 1
        self._init_weights()
        self.heads = nn.ModuleList(Heads(self.backbone.out_channels, cfg) for _ in range(n_stages))

    def _init_weights(self) -> None:
        for m in self.backbone.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        for m in self.backbone.modules():  # each residual branch starts as identity (Goyal et al. 2017)
            if isinstance(m, BasicBlock):
                nn.init.zeros_(m.bn2.weight)

    def forward_stages(self, image: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        """image (B, 3, Hp, Wp) -> per stack {"heat": logits (B, 1, h, w), "offset": (B, 2, h, w), "radius": (B, 1, h, w)}."""
        x = (image - self.mean) / self.std
        return [head(f) for head, f in zip(self.heads, self.backbone(x))]

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """image (B, 3, Hp, Wp) -> heat (B, 1, h, w) in (0, 1), offset (B, 2, h, w), radius (B, 1, h, w)."""
        out = self.forward_stages(image)[-1]
        return torch.sigmoid(out["heat"]), out["offset"], out["radius"]


@torch.no_grad()
def decode(heat: torch.Tensor, offset: torch.Tensor, radius: torch.Tensor, top_k: int = 100,
           image_size: tuple[int, int] | None = None) -> torch.Tensor:
    """Circles from the heads: 3x3 max-pool peaks, the top_k best.

    heat: (B, 1, h, w) probabilities; offset: (B, 2, h, w); radius: (B, 1, h, w), grid units.
    image_size: (H, W) px; cells whose centre lies in the padding are not peaks.
    Returns (B, K, 4): (cx, cy, r, score), px, by decreasing score (K = min(top_k, h * w)).
    Same rule as ``imaging.decode_numpy``, used with ONNX Runtime.
    """
    b, _, h, w = heat.shape
    peaks = torch.where(F.max_pool2d(heat, 3, 1, 1) == heat, heat, torch.zeros_like(heat))
    if image_size is not None:  # a cell's centre pixel is 4j + 1.5
        rows = torch.arange(h, device=heat.device) * STRIDE + (STRIDE - 1) / 2 <= image_size[0] - 0.5
        cols = torch.arange(w, device=heat.device) * STRIDE + (STRIDE - 1) / 2 <= image_size[1] - 0.5
        peaks = peaks * (rows[:, None] & cols[None, :])
    score, idx = peaks.reshape(b, -1).topk(min(top_k, h * w), dim=1)
    ys, xs = torch.div(idx, w, rounding_mode="floor"), idx % w
    off = offset.flatten(2).gather(2, idx[:, None, :].expand(-1, 2, -1))  # (B, 2, K)
    rad = radius.flatten(2).gather(2, idx[:, None, :])  # (B, 1, K)
    cx = (xs + off[:, 0]) * STRIDE - 0.5
    cy = (ys + off[:, 1]) * STRIDE - 0.5
    r = rad[:, 0].clamp(min=0) * STRIDE
    return torch.stack([cx, cy, r, score], dim=2)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())

