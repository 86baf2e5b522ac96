"""Autoencoders of the thesis, sized for a CPU (training only: imports torch).

- ``dalsr``: denoising autoencoder, pixel L2 (DALSR-Pose).
- ``cvml``: variational autoencoder, loss = sum ||x_hat - x'||^2 + alpha * KL, alpha = 0.1
  (CVML-Pose); inference uses mu.
- ``cvam``: conditional VAE: the one-hot object label is tiled and concatenated to the
  input of every conv layer of encoder and decoder (CVAM-Pose, Table 4.12).

Encoders: ``plain`` (strided convs, CVML-base), ``resnet`` (residual blocks with a
strided 1x1 shortcut, the ResNet-style encoder of CVML-18 at CPU width; for cvam the label
goes into every block), or ``lite0``/``lite1``/``lite2``: an ImageNet-pretrained
EfficientNet-Lite trunk (:mod:`tracker.training.nets.backbone`, BatchNorm frozen), a 1x1 conv to
128 channels and the latent layers (for cvam the label joins there: the pretrained layers
take images only). ``nanodet``: the COCO-pretrained NanoDet backbone
(:mod:`tracker.training.nets.nanodet`, pretrained for detection): its stem and stages 1-3
(through stride 16) frozen, so their outputs can be cached per crop
(:class:`tracker.training.nets.fit.CachedInputs`), stage 4 trained, then the same 1x1 conv and
latent layers; ``nanodet32``: stage 4 frozen too. Every conv of encoder and decoder is followed
by BatchNorm (``norm``, on by default; export folds it into the conv) and SiLU, nearest-neighbour
upsampling + conv
decoder (no transposed convolutions). Without the BatchNorm, training from scratch sat for
~500 steps at the per-object mean image (validation L2 ~330 on a two-object build; a plain
autoencoder without the VAE's noise saturated at the black image and never left it); with it
the same crops passed that level after 150 steps (docs/experiments/stop-45.md). The encoder's
``forward`` returns ``mu`` only: that is what is exported to ONNX.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

METHODS = ("dalsr", "cvml", "cvam")
PRETRAINED = ("lite0", "lite1", "lite2")
# a frozen front whose outputs training caches: NanoDet's backbone frozen through stage 3
# (stride 16; stage 4 trained) or through stage 4 (stride 32; only the layers after it trained)
FROZEN_THROUGH = {"nanodet": 3, "nanodet32": 4}
FROZEN = tuple(FROZEN_THROUGH)
ENCODERS = ("plain", "resnet") + PRETRAINED + FROZEN
TRUNK_REDUCED = 128  # channels of the pretrained trunk's features after the 1x1 conv


def crop_size_problem(encoder: str, size) -> str | None:
    """Why the ``encoder`` trunk cannot take square crops of ``size`` pixels (None: it can): the
    plain and ResNet trunks halve the crop four times, the pretrained ones five (a plain trunk
    given 70 pixels would reconstruct 64 and the loss would compare unequal images)."""
    step = 32 if encoder in PRETRAINED + FROZEN else 16
    if isinstance(size, bool) or not isinstance(size, int) or size < step or size % step:
        return (f"--encoder {encoder} takes crops a multiple of {step} pixels a side "
                f"(e.g. --size {128 if step == 32 else 64}), not {size}")
    return None


class CondConv(nn.Module):
    """Conv (+ BatchNorm) (+ SiLU) whose input gets the tiled one-hot label when ``n_cond`` > 0."""

    def __init__(self, cin, cout, n_cond, stride=1, act=True, norm=True):
        super().__init__()
        self.n_cond = n_cond
        self.conv = nn.Conv2d(cin + n_cond, cout, 3 if stride == 1 else 4, stride, 1)
        self.norm = nn.BatchNorm2d(cout) if norm else nn.Identity()
        self.act = nn.SiLU() if act else nn.Identity()

    def forward(self, x, c=None):
        if self.n_cond:
            x = torch.cat([x, c[:, :, None, None].expand(-1, -1, x.shape[2], x.shape[3])], 1)
        return self.act(self.norm(self.conv(x)))


class CondResBlock(nn.Module):
    """Downsampling residual block: two convs (the label tiled into both) + a strided 1x1
    shortcut, SiLU after the sum."""

    def __init__(self, cin, cout, n_cond, norm=True):
        super().__init__()
        self.conv1 = CondConv(cin, cout, n_cond, stride=2, norm=norm)
        self.conv2 = CondConv(cout, cout, n_cond, act=False, norm=norm)
        # the strided 1x1 shortcut as subsampling + a stride-1 1x1 conv (the same function):
        # oneDNN's strided 1x1 weight gradient corrupted the heap on small maps (torch 2.13, AVX2)
        self.skip = nn.Conv2d(cin, cout, 1, 1)

    def forward(self, x, c=None):
        return F.silu(self.conv2(self.conv1(x, c), c) + self.skip(x[:, :, ::2, ::2]))


class Encoder(nn.Module):
    def __init__(self, size=64, latent=128, widths=(32, 64, 128, 256), n_cond=0, variational=True,
                 arch: str = "plain", pretrained: bool = True, norm: bool = True):
        super().__init__()
        if arch not in ENCODERS:
            raise ValueError(f"unknown encoder {arch}")
        self.size, self.latent, self.n_cond, self.variational = size, latent, n_cond, variational
        self.trunk = self.frozen = None
        if arch in FROZEN:
            from tracker.training.nets.nanodet import NanoDet, load_weights
            if size % 32:
                raise ValueError(f"the NanoDet trunk needs a crop size that is a multiple of 32, not {size}")
            bb = (load_weights(NanoDet(coco_head=False)) if pretrained else NanoDet(coco_head=False)).backbone
            stages, k = [bb.stem, bb.stage1, bb.stage2, bb.stage3, bb.stage4], FROZEN_THROUGH[arch]
            self.frozen = nn.Sequential(*stages[:k + 1]).requires_grad_(False)
            self.trunk = nn.Sequential(*stages[k + 1:])  # (empty: the identity)
            self.reduce = nn.Conv2d(512, TRUNK_REDUCED, 1)
            self.convs = nn.ModuleList()
            self.feat, cin = size // 32, TRUNK_REDUCED
        elif arch in PRETRAINED:
            from tracker.training.nets.backbone import FEATURES, LiteTrunk
            if size % 32:
                raise ValueError(f"a pretrained trunk needs a crop size that is a multiple of 32, not {size}")
            self.trunk = LiteTrunk(arch, pretrained)
            self.reduce = nn.Conv2d(FEATURES, TRUNK_REDUCED, 1)
            self.convs = nn.ModuleList()
            self.feat, cin = size // 32, TRUNK_REDUCED
        else:
            layers, cin = [], 3
            for w in widths:
                layers.append(CondResBlock(cin, w, n_cond, norm) if arch == "resnet"
                              else CondConv(cin, w, n_cond, stride=2, norm=norm))
                cin = w
            self.convs = nn.ModuleList(layers)
            self.feat = size // 2 ** len(widths)
        flat = cin * self.feat * self.feat
        self.mu = nn.Linear(flat + n_cond, latent)
        self.logvar = nn.Linear(flat + n_cond, latent) if variational else None

    def features(self, x, c=None):
        """x: RGB crops (B, 3, S, S), or for a frozen front its outputs (cached) to go on from."""
        if self.frozen is not None and x.shape[1] == 3:
            x = self.frozen(x)
        if self.trunk is not None:
            x = F.silu(self.reduce(self.trunk(x)))
        for layer in self.convs:
            x = layer(x, c)
        h = x.flatten(1)
        return torch.cat([h, c], 1) if self.n_cond else h

    def forward(self, x, c=None):
        """mu only (the exported inference path). x: (B, 3, S, S) RGB in [0, 1]."""
        return self.mu(self.features(x, c))

    def encode(self, x, c=None):
        h = self.features(x, c)
        mu = self.mu(h)
        return mu, (self.logvar(h) if self.variational else None)


class Decoder(nn.Module):
    def __init__(self, size=64, latent=128, widths=(256, 128, 64, 32), n_cond=0, norm=True):
        super().__init__()
        self.n_cond = n_cond
        self.feat = size // 2 ** len(widths)
        self.w0 = widths[0]
        self.fc = nn.Linear(latent + n_cond, widths[0] * self.feat * self.feat)
        ups, cin = [], widths[0]
        # the last upsampling conv works at full resolution: half the width keeps it cheap
        for w in widths[1:] + (max(widths[-1] // 2, 8),):
            ups.append(CondConv(cin, w, n_cond, norm=norm))
            cin = w
        self.ups = nn.ModuleList(ups)
        self.out = nn.Conv2d(cin, 3, 3, 1, 1)

    def forward(self, z, c=None):
        if self.n_cond:
            z = torch.cat([z, c], 1)
        x = F.silu(self.fc(z)).view(-1, self.w0, self.feat, self.feat)
        for layer in self.ups:
            x = layer(F.interpolate(x, scale_factor=2, mode="nearest"), c)
        return torch.sigmoid(self.out(x))


class AutoEncoder(nn.Module):
    def __init__(self, method="cvam", size=64, latent=128, n_objects=1, widths=(32, 64, 128, 256),
                 encoder: str = "plain", pretrained: bool = True, norm: bool = True, recon_size: int | None = None):
        """``recon_size``: the decoder's output size (default ``size``): a 128-pixel input can be
        reconstructed at 64 pixels, the decoder's cost a quarter."""
        super().__init__()
        if method not in METHODS:
            raise ValueError(f"unknown method {method}")
        self.method = method
        n_cond = n_objects if method == "cvam" else 0
        variational = method in ("cvml", "cvam")
        self.encoder = Encoder(size, latent, widths, n_cond, variational, arch=encoder, pretrained=pretrained,
                               norm=norm)
        self.decoder = Decoder(recon_size or size, latent, tuple(reversed(widths)), n_cond, norm=norm)
        self.n_cond = n_cond

    def forward(self, x, c=None):
        mu, logvar = self.encoder.encode(x, c)
        z = mu
        if logvar is not None and self.training:
            z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
        return self.decoder(z, c), mu, logvar


def loss_terms(recon, target, mu, logvar):
    """Per-batch mean of: sum of squared pixel errors per image, and KL to N(0, I); float32
    whatever the arithmetic of the forward pass."""
    recon, mu = recon.float(), mu.float()
    l2 = ((recon - target) ** 2).flatten(1).sum(1).mean()
    if logvar is None:
        return l2, torch.zeros((), device=recon.device)
    logvar = logvar.float()
    kl = (-0.5 * (1 + logvar - mu ** 2 - logvar.exp()).sum(1)).mean()
    return l2, kl
