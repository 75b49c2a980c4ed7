"""Image features of maps for the realism and control-fidelity metrics (paper §3.3).

Every map becomes a 128 x 128 RGB raster in one style, so HD maps and SD maps are comparable:
R marks where lanes (HD) or roads (SD) are, G and B hold the travel direction as
``0.5 * (cos h, sin h) + 0.5`` where it is known (lanes, one-way roads) and 0.5 on two-way roads.
A ResNet-50 trunk turns rasters into 2048-d globally pooled features. Backbones:

- ``resnet50-imagenet``: torchvision's ImageNet weights, read from a local file (``.pth`` or
  ``.safetensors``) or the torch hub cache; paper-faithful. Nothing is downloaded.
- ``resnet50-seeded``: a deterministic random initialisation (seed 0); works offline.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import torch

from cmtool.core.errors import CmtoolError
from cmtool.core.geometry import CV_SHIFT, ego_to_pixel
from cmtool.data.sd_raster import decode_sd

BACKBONES = ("resnet50-seeded", "resnet50-imagenet")
IMAGE_PX = 128
IMAGENET_FILE = "resnet50-11ad3fa6.pth"  # torchvision's ResNet50_Weights.IMAGENET1K_V2 file name
_MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
_STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


def lanes_image(lanes, frame_m: float = 64.0, size: int = IMAGE_PX) -> np.ndarray:
    """A lane set (ego-frame polylines, metres) as a feature raster: 1 m wide lines, direction in G, B."""
    img = np.zeros((size, size, 3), np.uint8)
    px = frame_m / size
    width = max(1, int(round(1.0 / px)))
    for lane in lanes:
        lane = np.asarray(lane, np.float64)
        if len(lane) < 2:
            continue
        pix = ego_to_pixel(lane, px, frame_m)
        d = np.diff(lane, axis=0)
        h = np.arctan2(d[:, 1], d[:, 0])
        g, b = np.round(255 * (0.5 * np.cos(h) + 0.5)), np.round(255 * (0.5 * np.sin(h) + 0.5))
        for k in range(len(d)):
            cv2.line(img, tuple(pix[k]), tuple(pix[k + 1]), (255, int(g[k]), int(b[k])), width, cv2.LINE_8, CV_SHIFT)
    return img


def sd_image(sd: np.ndarray) -> np.ndarray:
    """An SD raster (docs/data.md: "Frames and rasters") as a feature raster in the same style as :func:`lanes_image`."""
    dec = decode_sd(sd)
    img = np.zeros(sd.shape[:2] + (3,), np.uint8)
    road = dec["road"]
    heading = np.nan_to_num(dec["heading"], nan=0.0)
    oneway = ~np.isnan(dec["heading"])
    img[..., 0] = np.where(road, 255, 0)
    img[..., 1] = np.where(road, np.where(oneway, np.round(255 * (0.5 * np.cos(heading) + 0.5)), 128), 0)
    img[..., 2] = np.where(road, np.where(oneway, np.round(255 * (0.5 * np.sin(heading) + 0.5)), 128), 0)
    if img.shape[0] != IMAGE_PX:
        img = cv2.resize(img, (IMAGE_PX, IMAGE_PX), interpolation=cv2.INTER_NEAREST)
    return img


def imagenet_weights(path=None) -> Path:
    """The ImageNet ResNet-50 weights file: ``path``, else torchvision's file in the torch hub cache."""
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise CmtoolError(f"{path}: no such weights file")
        return path
    hub = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch")) / "hub" / "checkpoints"
    found = sorted(hub.glob("resnet50-*.pth")) if hub.is_dir() else []
    if not found:
        raise CmtoolError(f"resnet50-imagenet: no ImageNet weights found; put torchvision's {IMAGENET_FILE} in {hub} "
                          "or pass --weights FILE (or use --backbone resnet50-seeded, which needs none)")
    return found[-1]


class FeatureExtractor:
    """ResNet-50 trunk -> (N, 2048) pooled features of uint8 RGB rasters (N, H, W, 3)."""

    def __init__(self, backbone: str = "resnet50-seeded", weights=None, device="cpu", batch: int = 64,
                 precision: str = "fp32"):
        from torchvision.models import resnet50

        if backbone not in BACKBONES:
            raise CmtoolError(f"unknown feature backbone {backbone!r} (choose {', '.join(BACKBONES)})")
        if precision not in ("fp32", "bf16"):
            raise CmtoolError(f"feature precision {precision!r} (choose fp32, bf16)")
        self.backbone, self.device, self.batch, self.precision = backbone, torch.device(device), batch, precision
        if backbone == "resnet50-seeded":
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(0)
                net = resnet50()
            self.source = "seeded random initialisation (seed 0)"
        else:
            file = imagenet_weights(weights)
            net = resnet50()
            state = _read_state(file)
            own = net.state_dict()
            wrong = [k for k in own if k not in state or tuple(state[k].shape) != tuple(own[k].shape)]
            if wrong:
                raise CmtoolError(f"{file}: not ResNet-50 weights ({len(wrong)} tensors missing or of another "
                                  f"shape, e.g. {wrong[0]})")
            net.load_state_dict(state)
            self.source = str(file)
        net.fc = torch.nn.Identity()
        self.net = net.eval().to(self.device, memory_format=torch.channels_last)

    @torch.inference_mode()
    def __call__(self, images: np.ndarray) -> np.ndarray:
        """Features of ``images`` in batches; under bf16 autocast with ``precision`` "bf16"."""
        out = []
        mean, std = _MEAN.to(self.device), _STD.to(self.device)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            for start in range(0, len(images), self.batch):
                x = torch.from_numpy(np.ascontiguousarray(images[start:start + self.batch])).to(self.device)
                x = ((x.permute(0, 3, 1, 2).float() / 255.0 - mean) / std).contiguous(memory_format=torch.channels_last)
                out.append(self.net(x).float().cpu().numpy())
        return np.concatenate(out) if out else np.zeros((0, 2048), np.float32)


def _read_state(path: Path) -> dict:
    """A state dict from ``.safetensors`` or a ``.pth`` (read with ``weights_only``, no arbitrary pickles)."""
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            return load_file(str(path))
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # a corrupt or foreign file
        raise CmtoolError(f"{path}: not ResNet-50 weights ({e})") from None
