"""A small anchor-free detector (CenterNet-style) for the CPU: a backbone to stride 32 (plain
convolutions from random weights, or an ImageNet-pretrained EfficientNet-Lite), a top-down
pathway back to stride 8, and three heads (class centre heatmaps, log box size, centre offset).
Output contract: ``tracker/runtime/detector.py``."""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from tracker.core.defaults import DETECTOR_BACKBONES


def cbr(cin, cout, stride=1, k=3):
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class CenterNetLite(nn.Module):
    def __init__(self, n_classes: int, width: int = 32):
        super().__init__()
        w = width
        self.n_classes = n_classes
        self.s2 = nn.Sequential(cbr(3, w // 2, 2), cbr(w // 2, w // 2))                      # 1/2
        self.s4 = nn.Sequential(cbr(w // 2, w, 2), cbr(w, w))                                # 1/4
        self.s8 = nn.Sequential(cbr(w, 2 * w, 2), cbr(2 * w, 2 * w))                        # 1/8
        self.s16 = nn.Sequential(cbr(2 * w, 3 * w, 2), cbr(3 * w, 3 * w))                    # 1/16
        self.s32 = nn.Sequential(cbr(3 * w, 4 * w, 2), cbr(4 * w, 4 * w))                    # 1/32
        self.lat16 = cbr(3 * w, 2 * w, k=1)
        self.top32 = cbr(4 * w, 2 * w, k=1)
        self.smooth16 = cbr(2 * w, 2 * w)
        self.lat8 = cbr(2 * w, 2 * w, k=1)
        self.smooth8 = cbr(2 * w, 2 * w)
        self.head_hm = nn.Sequential(cbr(2 * w, 2 * w), nn.Conv2d(2 * w, n_classes, 1))
        self.head_box = nn.Sequential(cbr(2 * w, 2 * w), nn.Conv2d(2 * w, 4, 1))
        nn.init.constant_(self.head_hm[-1].bias, -math.log((1 - 0.01) / 0.01))  # prior 0.01 (focal-loss init)

    def forward_logits(self, x):
        x8 = self.s8(self.s4(self.s2(x)))
        x16 = self.s16(x8)
        x32 = self.s32(x16)
        p16 = self.smooth16(self.lat16(x16) + F.interpolate(self.top32(x32), size=x16.shape[-2:], mode="nearest"))
        p8 = self.smooth8(self.lat8(x8) + F.interpolate(p16, size=x8.shape[-2:], mode="nearest"))
        return self.head_hm(p8), self.head_box(p8)

    def forward(self, x):
        """The exported graph: (B, C + 4, h, w) with sigmoid heatmaps."""
        hm, box = self.forward_logits(x)
        return torch.cat([torch.sigmoid(hm), box], 1)


class CenterNetPretrained(nn.Module):
    """The same heads and top-down pathway as :class:`CenterNetLite` on an ImageNet-pretrained
    EfficientNet-Lite trunk (:mod:`tracker.training.nets.backbone`, BatchNorm frozen): its stride
    8 / 16 / 32 features, each brought to ``2 x width`` channels by a 1x1 convolution, merged
    top-down to stride 8. Takes the weights' input range: the detector spec's mean 127/255 and
    std 128/255 (:data:`IMAGENET_MEAN_STD`)."""

    def __init__(self, n_classes: int, width: int = 32, trunk: str = "lite0", pretrained: bool = True):
        super().__init__()
        from tracker.training.nets.backbone import LiteTrunk
        w = 2 * width
        self.n_classes = n_classes
        self.trunk = LiteTrunk(trunk, pretrained)
        c8, c16, c32 = self.trunk.pyramid_channels()
        self.lat8, self.lat16, self.top32 = cbr(c8, w, k=1), cbr(c16, w, k=1), cbr(c32, w, k=1)
        self.smooth16, self.smooth8 = cbr(w, w), cbr(w, w)
        self.head_hm = nn.Sequential(cbr(w, w), nn.Conv2d(w, n_classes, 1))
        self.head_box = nn.Sequential(cbr(w, w), nn.Conv2d(w, 4, 1))
        nn.init.constant_(self.head_hm[-1].bias, -math.log((1 - 0.01) / 0.01))

    def train(self, mode: bool = True):
        super().train(mode)
        self.trunk.train(mode)  # the trunk's BatchNorms stay frozen
        return self

    def forward_logits(self, x):
        x8, x16, x32 = self.trunk.pyramid(x)
        p16 = self.smooth16(self.lat16(x16) + F.interpolate(self.top32(x32), size=x16.shape[-2:], mode="nearest"))
        p8 = self.smooth8(self.lat8(x8) + F.interpolate(p16, size=x8.shape[-2:], mode="nearest"))
        return self.head_hm(p8), self.head_box(p8)

    forward = CenterNetLite.forward


class CenterNetCoco(nn.Module):
    """The same kind of heads on NanoDet's COCO-pretrained trunk and PAN neck
    (:mod:`tracker.training.nets.nanodet`; its BatchNorms are folded into its convolutions, so
    the whole trunk trains): the neck's stride-8 map (128 channels, already merged with strides
    16 and 32) under two full-width heads (two 3x3 convolutions of 128 channels each). Takes RGB
    in 0..1 (the detector spec's mean 0, std 1: :data:`COCO_MEAN_STD`). ``pretrained`` False:
    the same network from random weights (the control)."""

    def __init__(self, n_classes: int, pretrained: bool = True):
        super().__init__()
        from tracker.training.nets.nanodet import NECK_CHANNELS, NanoDet, nanodet_coco
        self.n_classes = n_classes
        self.trunk = nanodet_coco().train() if pretrained else NanoDet()
        self.trunk.coco_head = None
        c = NECK_CHANNELS
        self.head_hm = nn.Sequential(cbr(c, c), cbr(c, c), nn.Conv2d(c, n_classes, 1))
        self.head_box = nn.Sequential(cbr(c, c), cbr(c, c), nn.Conv2d(c, 4, 1))
        nn.init.constant_(self.head_hm[-1].bias, -math.log((1 - 0.01) / 0.01))

    def forward_logits(self, x):
        p8 = self.trunk.features(x)[0]
        return self.head_hm(p8), self.head_box(p8)

    forward = CenterNetLite.forward


class Logits(nn.Module):
    """A detector's training outputs (heatmap logits, box maps) as its ``forward``: the module
    that DistributedDataParallel wraps (it synchronises gradients of ``forward`` calls only)."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x):
        return self.net.forward_logits(x)


IMAGENET_MEAN_STD = (127.0 / 255.0, 128.0 / 255.0)  # the pretrained trunks' (255 x - 127) / 128
COCO_MEAN_STD = (0.0, 1.0)  # NanoDet's: RGB / 255
BACKBONES = DETECTOR_BACKBONES


def make_detector(n_classes: int, width: int = 32, backbone: str = "plain", pretrained: bool = True) -> nn.Module:
    """``plain``: :class:`CenterNetLite` from random weights; ``lite0``..``lite2``:
    :class:`CenterNetPretrained` on that trunk (ImageNet weights unless ``pretrained`` is False);
    ``nanodet``: :class:`CenterNetCoco` (COCO weights unless ``pretrained`` is False)."""
    if backbone == "plain":
        return CenterNetLite(n_classes, width)
    if backbone == "nanodet":
        return CenterNetCoco(n_classes, pretrained)
    return CenterNetPretrained(n_classes, width, backbone, pretrained)


def focal_loss(logits, target):
    """CenterNet's penalty-reduced focal loss on Gaussian centre heatmaps, per positive."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target.eq(1).float()
    neg = 1 - pos
    pos_loss = torch.log(p) * (1 - p) ** 2 * pos
    neg_loss = torch.log(1 - p) * p ** 2 * (1 - target) ** 4 * neg
    n = pos.sum().clamp(min=1)
    return -(pos_loss.sum() + neg_loss.sum()) / n


def convs_in_order(model: nn.Module) -> list[nn.Conv2d]:
    """The model's convolutions in the order its forward pass runs them (the order of the
    Conv nodes in its exported graph)."""
    order = []
    hooks = [m.register_forward_hook(lambda m, i, o: order.append(m)) for m in model.modules() if isinstance(m, nn.Conv2d)]
    was_training = model.training
    try:
        with torch.no_grad():
            model.eval()(torch.zeros(1, 3, 64, 64))
    finally:
        for h in hooks:
            h.remove()
        model.train(was_training)
    return order


def state_from_export(model: CenterNetLite, conv_weights: list[tuple]) -> dict:
    """A state dict for ``model`` from its exported graph's convolutions, given as
    ``[(weight, bias), ...]`` in graph order. The export folded each BatchNorm into the conv
    before it, so that conv takes the folded weight and its BatchNorm becomes the identity plus
    the folded bias (scale 1, mean 0, variance 1 - eps): the same function while the
    BatchNorms stay frozen (``freeze_batchnorm``). ValueError where the shapes do not match."""
    convs = convs_in_order(model)
    if len(convs) != len(conv_weights):
        raise ValueError(f"{len(conv_weights)} convolutions, this network has {len(convs)}")
    names = {m: n for n, m in model.named_modules()}
    modules = dict(model.named_modules())
    sd = {k: v.clone() for k, v in model.state_dict().items()}
    for conv, (w, b) in zip(convs, conv_weights):
        name = names[conv]
        if tuple(w.shape) != tuple(conv.weight.shape) or b is None or len(b) != conv.out_channels:
            raise ValueError(f"a convolution of shape {tuple(w.shape)} where this network has {tuple(conv.weight.shape)}")
        sd[name + ".weight"] = torch.from_numpy(np.array(w, np.float32))
        if conv.bias is not None:
            sd[name + ".bias"] = torch.from_numpy(np.array(b, np.float32))
            continue
        parent, i = name.rsplit(".", 1)
        bn_name = f"{parent}.{int(i) + 1}"
        bn = modules.get(bn_name)
        if not isinstance(bn, nn.BatchNorm2d):
            raise ValueError(f"{name} has no bias and no BatchNorm after it")
        sd[bn_name + ".weight"] = torch.ones(conv.out_channels)
        sd[bn_name + ".bias"] = torch.from_numpy(np.array(b, np.float32))
        sd[bn_name + ".running_mean"] = torch.zeros(conv.out_channels)
        sd[bn_name + ".running_var"] = torch.full((conv.out_channels,), 1.0 - bn.eps)
    return sd


def freeze_batchnorm(model: nn.Module) -> None:
    """Keep every BatchNorm on its stored statistics (eval mode) while the rest trains."""
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.eval()
