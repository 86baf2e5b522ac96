"""The training commands: ``train`` (autoencoder, pose heads, codebook -> a bundle) and
``train-detector`` (the 2D detector, added to a bundle). The training code (tracker.training,
torch) is imported only when a command runs."""
from __future__ import annotations

import sys

from tracker.cli.args import (add_precision, add_regressor_budget, fraction, nonnegative_int, positive_float,
                              positive_int)
from tracker.cli.common import print_validation
from tracker.core.defaults import DETECTOR_BACKBONES, LR_SCHEDULES
from tracker.runtime.signals import sigterm_as_ctrl_c


def add_train(sub, REPO) -> None:
    """``app.py train``: autoencoder + latent regressors (+ AAE codebook) -> bundle."""
    s = sub.add_parser("train", help="autoencoder + latent regressors (+ AAE codebook) -> model bundle")
    s.add_argument("--data", required=True, help="a 'synth' split")
    s.add_argument("--out", required=True, help="bundle folder, e.g. models/lmo")
    s.add_argument("--method", choices=["dalsr", "cvml", "cvam"], default="cvam")
    s.add_argument("--encoder", choices=["plain", "resnet", "lite0", "lite1", "lite2", "nanodet", "nanodet32"],
                   default="plain",
                   help="plain strided convs (CVML-base), residual blocks (CVML-18 style), an ImageNet-pretrained "
                        "EfficientNet-Lite trunk (lite0/1/2, fine-tuned with its BatchNorm frozen), or the "
                        "COCO-pretrained NanoDet backbone (nanodet: frozen through stride 16, its outputs cached, "
                        "stage 4 trained; nanodet32: stage 4 frozen too; reconstructs at 64 px); pretrained trunks "
                        "take crops a multiple of 32 px, e.g. --size 128")
    s.add_argument("--no-pretrained", action="store_true",
                   help="with --encoder lite*: the same network from random weights, BatchNorm learning (the control)")
    s.add_argument("--lr", type=positive_float, default=1e-3, help="the autoencoder's AdamW learning rate")
    s.add_argument("--batch", type=positive_int, default=128, help="the autoencoder's batch size")
    s.add_argument("--lr-schedule", choices=LR_SCHEDULES, default="plateau",
                   help="the autoencoder's step size: divided by 5 after 3 epochs without a better validation L2 "
                        "(plateau), or annealed by a cosine over --minutes (budget; no better on dev, stop 50)")
    s.add_argument("--head-sets", type=positive_int, default=1, metavar="N",
                   help="pose-head sets fitted with seeds seed, seed+1, ... and averaged, each with --reg-minutes")
    s.add_argument("--kl-warmup", type=nonnegative_int, default=0, metavar="STEPS",
                   help="variational methods: raise the KL term's weight from 0 over this many steps (0: full "
                        "weight from the start)")
    s.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="where the autoencoder trains: a CUDA GPU where torch sees one (auto), or the CPU")
    s.add_argument("--size", type=positive_int, default=64, help="crop side in pixels (thesis: 128)")
    s.add_argument("--latent", type=positive_int, default=128)
    s.add_argument("--minutes", type=positive_float, default=45.0, help="autoencoder time budget")
    add_regressor_budget(s)
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--max-images", type=positive_int, help="use only the first N scene images")
    s.add_argument("--models-info", help="models_info.json (default: computed from the meshes)")
    s.add_argument("--init-from", metavar="CKPT",
                   help="start from another run's ae_checkpoint.pt (same network), e.g. to train on more data")
    add_precision(s)
    s.set_defaults(func=cmd_train)


def cmd_train(args) -> int:
    sigterm_as_ctrl_c()
    from tracker.training.train import train_bundle
    m = train_bundle(args.data, args.out, method=args.method, size=args.size, latent=args.latent,
                     minutes=args.minutes, seed=args.seed, max_images=args.max_images,
                     models_info_path=args.models_info, reg_minutes=args.reg_minutes, encoder=args.encoder,
                     init_from=args.init_from, precision=args.precision, reg_epochs=args.reg_epochs,
                     lr=args.lr, batch=args.batch, pretrained=not args.no_pretrained, device=args.device,
                     kl_warmup=args.kl_warmup, lr_schedule=args.lr_schedule, head_sets=args.head_sets,
                     command="app.py " + " ".join(sys.argv[1:]))
    if m is None:  # a helper process of a torchrun job: the first process writes the bundle
        return 0
    print_validation(args.out, m)
    return 0


def add_train_detector(sub, REPO) -> None:
    """``app.py train-detector``: the 2D detector, added to a bundle."""
    s = sub.add_parser("train-detector", help="train the 2D detector on synth scenes and add it to a bundle",
                       description="Train the 2D detector on synth scenes and add it to a bundle. Under "
                                   "'torchrun --nproc_per_node N app.py train-detector ...' N processes (GPUs, or "
                                   "CPU processes with gloo) share every batch.")
    s.add_argument("--data", required=True, help="a 'synth' split")
    s.add_argument("--model", required=True, help="the bundle that gets detector.onnx")
    s.add_argument("--minutes", type=positive_float, default=60.0, help="training time budget (cosine schedule over it)")
    s.add_argument("--width", type=positive_int, default=32, help="base channel width of the network")
    s.add_argument("--input", type=positive_int, nargs=2, default=(320, 240), metavar=("W", "H"), help="network input size")
    s.add_argument("--batch", type=positive_int, default=32)
    s.add_argument("--lr", type=positive_float, default=2e-3, help="peak learning rate (lower to fine-tune)")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--max-images", type=positive_int, default=None, help="use only the first N images")
    s.add_argument("--init-from", metavar="CKPT|BUNDLE",
                   help="start from another run's detector_ckpt_*.pt (same width and classes), e.g. to fine-tune on "
                        "new data, or from a bundle whose detector is one float network (its weights read back from "
                        "the ONNX graph; its BatchNorms then stay frozen)")
    s.add_argument("--boxes", choices=("visible", "amodal"), default="visible",
                   help="what the boxes cover: the visible part of each object, or its whole silhouette clipped "
                        "to the image (amodal: size and centre follow the object behind occluders)")
    s.add_argument("--occlusion", type=fraction, default=0.0, metavar="P",
                   help="share of training images that get clutter pasted over them (occlusion augmentation)")
    s.add_argument("--paste-objects", type=fraction, default=0.0, metavar="P",
                   help="share of those pasted rectangles cut around another image's object, which then "
                        "becomes a target too (objects in front of objects)")
    s.add_argument("--cutouts", metavar="DIR",
                   help="folder of RGBA images of things cut out of their background (PNG with alpha), "
                        "pasted over training images as real clutter that is not a target (docs/experiments/)")
    s.add_argument("--cutout-share", type=fraction, default=None, metavar="P",
                   help="share of training images that get 1-3 cut-outs pasted over them (with --cutouts; default 0.5)")
    s.add_argument("--colour", choices=("standard", "strong", "mild"), default="standard",
                   help="photometric augmentation: brightness, contrast, saturation, white balance, blur and noise; "
                        "'strong' adds grey-scale blends, per-channel gains and offsets, hue turns, inverted "
                        "channels and wider blurs (as detectors trained on renders for BOP do); 'mild' leaves "
                        "out saturation and white balance (the objects' colours kept)")
    s.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="validate and export the exponential moving average of the weights with this decay "
                        "(e.g. 0.999: about the last 1,000 steps) instead of the last weights; 0: off")
    s.add_argument("--backbone", choices=DETECTOR_BACKBONES, default="plain",
                   help="plain: the small convolutional backbone from random weights; lite0-2: an ImageNet-pretrained "
                        "EfficientNet-Lite trunk (BatchNorm frozen) under the same neck and heads; nanodet: NanoDet's "
                        "COCO-pretrained trunk and neck (tracker/training/pretrained/NOTICE.md) under full-width heads")
    s.add_argument("--no-pretrained", action="store_true",
                   help="with --backbone lite* or nanodet: the same network from random weights (the control)")
    s.add_argument("--freeze-through", default=None, metavar="STAGE",
                   help="with --backbone nanodet: keep the COCO backbone's weights from its stem through this "
                        "stage (stem, stage1 .. stage4; stage2: stride 8, stage3: stride 16; no backward pass "
                        "through it) and train the rest")
    s.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="where the detector trains: a CUDA GPU where torch sees one (auto), or the CPU")
    add_precision(s)
    s.set_defaults(func=cmd_train_detector)


def cmd_train_detector(args) -> int:
    sigterm_as_ctrl_c()
    from tracker.training.detector_train import train_detector
    d = train_detector(args.data, args.model, minutes=args.minutes, width=args.width, input_w=args.input[0],
                       input_h=args.input[1], batch=args.batch, seed=args.seed, max_images=args.max_images,
                       lr=args.lr, init_from=args.init_from, occlusion=args.occlusion, paste_objects=args.paste_objects,
                       cutouts=args.cutouts, cutout_share=args.cutout_share,
                       precision=args.precision, box_kind=args.boxes, colour=args.colour, ema=args.ema,
                       backbone=args.backbone, pretrained=not args.no_pretrained, device=args.device,
                       freeze_through=args.freeze_through, command="app.py " + " ".join(sys.argv[1:]))
    if d is None:  # a helper process of a torchrun job: the first process writes the bundle
        return 0
    v = d["training"]["validation_synthetic"]
    from tracker.evaluation.report import fmt_num
    print(f"detector added to {args.model}: synthetic validation AP {fmt_num(v['ap'])}, AP50 {fmt_num(v['ap50'])}")
    return 0
