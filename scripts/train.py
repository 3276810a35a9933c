"""`spherebench train`: train the CircleNet-style 2D baseline on a training dataset.

    spherebench train --data data/train [--data data/train-stereo] --out checkpoints/circlenet
                      [--backbone resnet18|hourglass]
                      [--resnet-width N] [--epochs N] [--seed N] [--onnx-weights float32|float16] [--resume]

Writes checkpoint.pt, history.json, training_curve.png, model.onnx and model_card.{json,md} to
--out (see spherebench.baselines.circlenet.train). Never train on the benchmark's scenes.
"""

from __future__ import annotations

import shlex
import sys
from dataclasses import replace

from spherebench import options
from spherebench.errors import SphereBenchError, require

#: the widest backbone taken: 4x ResNet-18's own (64); 100,000 asked for a 360 GB tensor
MAX_RESNET_WIDTH = 256


def add_arguments(parser) -> None:
    parser.add_argument("--data", required=True, action="append", metavar="DIR",
                        help="training dataset folder (the train preset); repeat to train on several as one "
                             "(e.g. train and train-stereo)")
    parser.add_argument("--out", type=options.out_path, required=True, metavar="DIR", help="folder for checkpoints, curve, model.onnx, card")
    parser.add_argument("--backbone", choices=["resnet18", "hourglass"], default=None,
                        help="resnet18 (light, CPU; default) or hourglass (CircleNet-HG-like, for a GPU)")
    parser.add_argument("--resnet-width", type=int, default=None, metavar="N",
                        help="resnet18 stage widths N, 2N, 4N, 8N (default 32: half width, for the CPU; "
                             "64: ResNet-18's own widths, for a GPU)")
    parser.add_argument("--image-size", default=None, metavar="WxH",
                        help="the model's input image size (default 424x240); other D435 modes of the same "
                             "aspect ratio are scaled to it")
    parser.add_argument("--epochs", type=int, default=None, metavar="N", help="epochs (default 20)")
    parser.add_argument("--batch-size", type=int, default=None, metavar="N", help="images per batch (default 16)")
    parser.add_argument("--seed", type=options.seed, default=0, metavar="N", help="seed of the split, init and augmentation")
    parser.add_argument("--device", default=None, help="auto (default), cpu, cuda, cuda:1, ...")
    parser.add_argument("--workers", type=options.loader_workers, default=None, metavar="N", help="data-loading processes (default 0)")
    parser.add_argument("--threads", type=options.threads, default=None, metavar="N",
                        help="CPU threads (default: one per core; 1 is faster when other jobs share the cores)")
    parser.add_argument("--onnx-weights", choices=["float32", "float16"], default=None,
                        help="how model.onnx stores its weights (default float32; float16 halves the file, "
                             "the arithmetic stays float32)")
    parser.add_argument("--resume", action="store_true", help="continue the interrupted run in --out")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    require("torch", "train", "training")
    # here, not at the top: they load torch (3 s), which `spherebench train --help` does not need
    from spherebench.baselines.circlenet.model import CircleNetConfig
    from spherebench.baselines.circlenet.train import TrainConfig, run_config, train

    given = {k: getattr(args, k) for k in ("epochs", "batch_size", "device", "workers", "threads", "onnx_weights")
             if getattr(args, k) is not None}
    if any(v < 1 for k, v in given.items() if k in ("epochs", "batch_size", "threads")):
        raise SphereBenchError("--epochs, --batch-size and --threads must be at least 1")
    model = {}
    if args.backbone is not None:
        model["backbone"] = args.backbone
    if args.image_size is not None:
        model["image_size"] = _parse_size(args.image_size)
    if args.resnet_width is not None:
        if not 1 <= args.resnet_width <= MAX_RESNET_WIDTH:
            raise SphereBenchError(f"--resnet-width {args.resnet_width}: give 1 to {MAX_RESNET_WIDTH} (64 is ResNet-18's "
                                   "own width; wider ones outgrow a machine's memory)")
        if args.backbone == "hourglass":
            raise SphereBenchError("--resnet-width sets the resnet18 backbone's widths; it has no effect on "
                                   "--backbone hourglass")
        model["resnet_width"] = args.resnet_width
    if args.resume:  # the run's own settings; an option given here must agree with them (train checks)
        config = run_config(args.out)
        config = replace(config, model=replace(config.model, **model), **given)
    else:
        config = TrainConfig(model=CircleNetConfig(**model), **given)
    command = "spherebench " + shlex.join(sys.argv[1:])
    data = args.data[0] if len(args.data) == 1 else args.data
    card = train(data, args.out, config, seed=args.seed, resume=args.resume, progress=not args.quiet,
                 command=command)
    v = card["val_onnx"]
    print(f"{args.out}/model.onnx: validation mAP {v['mAP']:.3f}, mAP.50 {v['mAP50']:.3f}, mAP.75 {v['mAP75']:.3f} "
          f"({card['epochs']} epochs, {card['train_seconds'] / 60:.1f} min)")
    return 0


def _parse_size(text: str) -> tuple[int, int]:
    """'424x240' -> (height, width) = (240, 424)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SphereBenchError(f"--image-size must be WIDTHxHEIGHT in pixels, e.g. 424x240, not {text!r}") from None
    return h, w
