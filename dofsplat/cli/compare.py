"""``dofsplat compare A B``: PSNR and SSIM between two images, a difference image on request."""

from __future__ import annotations

import math
import sys
from pathlib import Path

from ..errors import DofsplatError
from .options import EXIT_OK, HelpFormatter, positive_number


def add_parser(commands) -> None:
    """The ``compare`` subcommand's options."""
    compare = commands.add_parser(
        "compare", allow_abbrev=False, formatter_class=HelpFormatter,
        help="PSNR and SSIM between two images",
        description="Print the PSNR (dB; inf for identical images) and the SSIM of two "
                    "images of the same size, measured on the displayed values: linear "
                    "colour clipped to 0..1 and sRGB-encoded (alpha is ignored).",
        epilog="example:\n  dofsplat compare demo.png reference.png --diff diff.png")
    compare.add_argument("a", metavar="A", help="first image: .png, .npy or .exr")
    compare.add_argument("b", metavar="B", help="second image, the same size")
    compare.add_argument("--diff", metavar="OUT",
                         help="also write the difference image, GAIN x |A - B| per channel "
                              "(.png, .npy or .exr)")
    compare.add_argument("--gain", metavar="GAIN", type=positive_number, default=10.0,
                         help="amplification of the difference image (default: 10)")
    compare.add_argument("--json", metavar="FILE.json",
                         help="also write the numbers as JSON (psnr_db is null for "
                              "identical images)")
    compare.add_argument("--space", choices=("srgb", "linear"), default="srgb",
                         help="compare the displayed sRGB values (default) or the linear ones")
    compare.add_argument("-q", "--quiet", action="store_true",
                         help="do not say which files were written")
    compare.set_defaults(run=run)


def run(args) -> int:
    """``dofsplat compare``: PSNR and SSIM between two images; a difference image on request."""
    import json

    from ..io import (atomic_write, check_output_path, check_writable_path, nonfinite_pixels,
                      read_image)
    from ..metrics import compare, write_difference

    outputs = {}
    if args.diff is not None:
        outputs["diff"] = check_output_path(args.diff)
    if args.json is not None:
        outputs["json"] = check_writable_path(args.json, "a file name for --json")
    inputs = {Path(args.a).resolve(), Path(args.b).resolve()}
    for role, path in outputs.items():
        if path.resolve() in inputs:
            raise DofsplatError(f"the --{role} output {path} would overwrite an input image")
    if "diff" in outputs and "json" in outputs and outputs["diff"].resolve() == outputs["json"].resolve():
        raise DofsplatError(f"--diff and --json name the same file: {outputs['diff']}")

    a, b = read_image(args.a), read_image(args.b)
    for name, image in ((args.a, a), (args.b, b)):
        bad = nonfinite_pixels(image[..., :3])
        if bad:  # (the metrics would say so too, without the file's name)
            raise DofsplatError(f"{name}: {bad:,} pixels with NaN or inf values")
    if a.shape[:2] != b.shape[:2]:
        raise DofsplatError(f"the images differ in size: {args.a} is {a.shape[1]}x{a.shape[0]} "
                            f"pixels, {args.b} is {b.shape[1]}x{b.shape[0]}")
    result = compare(a, b, space=args.space)

    if "diff" in outputs:
        write_difference(outputs["diff"], a, b, gain=args.gain, space=args.space)
    if "json" in outputs:
        identical = math.isinf(result["psnr"])
        record = {"a": str(args.a), "b": str(args.b), "width": int(a.shape[1]),
                  "height": int(a.shape[0]), "space": result["space"],
                  "psnr_db": None if identical else result["psnr"],  # null: identical, PSNR inf
                  "identical": identical, "ssim": result["ssim"], "mse": result["mse"]}
        text = json.dumps(record, indent=2) + "\n"
        atomic_write(outputs["json"], lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
    print(f"PSNR {result['psnr']:.2f} dB  SSIM {result['ssim']:.4f}")
    if outputs and not args.quiet:
        print(f"wrote {', '.join(str(p) for p in outputs.values())}", file=sys.stderr)
    return EXIT_OK
