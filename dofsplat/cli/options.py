"""What the commands share before any work: argument types, option groups, help layout.

Every argument type raises ``argparse.ArgumentTypeError``, which argparse reports on one line;
:class:`Parser` turns every usage mistake into a :class:`~dofsplat.errors.DofsplatError`, which
:func:`dofsplat.cli.main` prints as one line and exit status 2.
"""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path

from ..errors import DofsplatError
from ..frame import MAX_LENS_SAMPLES, MAX_LOD_MIN_NODE, RenderSettings

EXIT_OK = 0
EXIT_USAGE = 2  # argparse's status for a usage error; every user mistake gets it
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for Ctrl-C

DEFAULT_SIZE = {"render": (512, 512), "demo": (800, 600)}  # pixels
DEFAULT_FOV_DEG = 40.0  # vertical field of view for ``render``
DEFAULT_SENSOR_WIDTH_MM = 36.0  # --focal-length-mm's sensor: full frame, as camera.photographic
DEFAULT_CUTOFF = 2.5  # the paper's c
APERTURE_PER_HALF_DIAGONAL = 0.1  # ``render``'s default lens diameter, x bbox half diagonal

UNITS = """\
units:
  Lengths (--eye, --target, --focus, --aperture, --focal-length, --frustum) are in world
  units, the units of the model's coordinates; --focal-length-mm and --sensor-width-mm in
  millimetres, with world units taken as metres (--scene-scale says otherwise). Image sizes and positions (--size,
  --focus-at) are in pixels, (0, 0) being the top-left corner of the image. Angles are in
  degrees. Colours are display (sRGB) values in 0..1.
"""

EPILOG = UNITS + """
examples:
  dofsplat demo
  dofsplat demo --size 1280x720 --aperture 0.3 -o wide.png
  dofsplat render scan.ply -o scan.png --focus-at 256 300
  dofsplat render scan.ply -o scan.exr --focal-length 0.05 --f-number 1.4 --focus 2.5
  dofsplat render scan.ply -o portrait.png --focal-length-mm 85 --f-number 1.4
  dofsplat render scan.ply -o scan.png --depth scan-depth.npy --stats scan.json
  dofsplat demo --method postfilter -o postfilter.png
  dofsplat reference --demo -o reference.png --samples 200
  dofsplat compare demo.png reference.png --diff diff.png
  dofsplat convert scan.laz -o scan-surfels.ply
"""


class HelpFormatter(argparse.HelpFormatter):
    """Wraps prose paragraphs; keeps indented blocks (the examples) as written."""

    def _fill_text(self, text, width, indent):
        paragraphs = []
        for block in text.strip("\n").split("\n\n"):
            lines = block.splitlines()
            if any(line.startswith(" ") for line in lines[1:]):
                paragraphs.append("\n".join(indent + line for line in lines))
            else:
                paragraphs.append(super()._fill_text(block, width, indent))
        return "\n\n".join(paragraphs)


class Parser(argparse.ArgumentParser):
    """argparse, but a usage mistake is one line on stderr (raised, printed by main)."""

    def error(self, message):
        raise DofsplatError(message)


# what ``render`` reads, for the help texts (dofsplat.io.LOADERS holds the loaders)
MODEL_EXTENSIONS = (".ply", ".ply.gz", ".obj", ".gltf", ".glb", ".stl", ".off", ".las", ".laz",
                     ".e57", ".pcd", ".spz", ".sog", ".dofsplat")


def add_input_options(p: argparse.ArgumentParser) -> None:
    """How a model file becomes surfels: the loader options (dofsplat.io.load's keywords)."""
    group = p.add_argument_group(
        "input", "How a file that is not a surfel file becomes surfels (docs/formats.md).")
    group.add_argument("--points", metavar="N", type=sample_count,
                       help="meshes: the number of surfels sampled over the surface "
                            "(default: the vertex count, at least 200000), or 'vertices' "
                            "for one surfel per vertex")
    group.add_argument("--texture", metavar="FILE",
                       help="meshes: an image applied through the texture coordinates "
                            "(for an OBJ that names no material file)")
    group.add_argument("--k", metavar="K", type=neighbour_count,
                       help="point clouds (PLY without faces, LAS/LAZ, E57, PCD): neighbours for "
                            "the normals, smoothing and radii (default: 24)")
    group.add_argument("--no-smooth", dest="smooth", action="store_false", default=None,
                       help="point clouds: keep the positions as measured (default: each "
                            "point is moved along its normal onto the plane of its K "
                            "neighbours, which removes scanner noise and quantisation); "
                            "meshes: samples on the flat triangles (default: on the Phong "
                            "tessellation that the vertex normals describe)")
    group.add_argument("--normalise", choices=("object", "render", "none"),
                       help="per-surfel normalisation, so that splats sum to 1 over the "
                            "surface (paper Section 6.3): object (neighbours' basis functions "
                            "summed in each surfel's tangent plane, seconds), render (the "
                            "paper's: weights read back from renders, slower) or none. "
                            "Default: object for points and meshes; a surfel or 3DGS file is "
                            "taken as it is")
    group.add_argument("--no-cache", action="store_true",
                       help="prepare the model again: neither read nor keep it in the cache "
                            "of prepared models (a point cloud or mesh that took over "
                            "0.5 s to prepare is kept there, keyed by the file's content and "
                            "these options; 'dofsplat cache' shows and clears it)")


# argparse reads a word that starts with "-" as an option, unless it is a plain negative
# number: "-2" and "-0.5" are values, "-320x240" and "-1e3" are unknown options. No option of
# dofsplat starts with "-" and a digit, so such a word is a value.
NEGATIVE_VALUE = re.compile(r"-\.?\d")
PLAIN_NEGATIVE_NUMBER = re.compile(r"-\d+|-\d*\.\d+")  # argparse's own test, whole word


def attach_negative_values(argv: list[str]) -> list[str]:
    """argv with a long option followed by a value that starts with "-" and a digit written
    as one word, "--size=-320x240": argparse would take "-320x240" for an option and say
    "--size: expected one argument"; attached, the value reaches the option's own check ("the
    image needs at least 1x1 pixels"). Plain negative numbers, which argparse reads as values
    (``--eye -1 2 3``), and the words after "--" are left as they are."""
    words = []
    i = 0
    while i < len(argv):
        word = argv[i]
        if word == "--":
            return words + argv[i:]
        value = argv[i + 1] if i + 1 < len(argv) else ""
        if (word.startswith("--") and "=" not in word and NEGATIVE_VALUE.match(value)
                and not PLAIN_NEGATIVE_NUMBER.fullmatch(value)):
            words.append(f"{word}={value}")
            i += 2
        else:
            words.append(word)
            i += 1
    return words


def prep_cache(args) -> str:
    """load()'s cache: "off" with --no-cache."""
    return "off" if getattr(args, "no_cache", False) else "auto"


def default_output(model: str) -> str:
    """``render``'s output without -o: the model's name with .png, in the current folder
    (``scans/lion.laz`` -> ``lion.png``, ``dragon.ply.gz`` -> ``dragon.png``)."""
    name = Path(model).name
    for ext in sorted(MODEL_EXTENSIONS, key=len, reverse=True):
        if name.lower().endswith(ext):
            name = name[:-len(ext)]
            break
    return (name or "render") + ".png"


# the input options, by the keyword of dofsplat.io.load that each one sets
LOADER_FLAGS = {"points": "--points", "texture": "--texture", "k": "--k",
                "smooth": "--no-smooth", "normalise": "--normalise"}


def loader_options(args) -> dict:
    """The input options the user gave, as keywords for dofsplat.io.load. An option that does
    not apply to the model file (--k for a mesh) is a DofsplatError naming the options as the
    user typed them (load's own error names its keywords: k, smooth)."""
    from ..io import model_options

    given = {n: getattr(args, n) for n in LOADER_FLAGS if getattr(args, n, None) is not None}
    if not given:
        return given
    what, accepted = model_options(args.input)
    wrong = [LOADER_FLAGS[n] for n in given if n not in accepted]
    if wrong:
        verb = "does" if len(wrong) == 1 else "do"
        takes = (", ".join(LOADER_FLAGS[n] for n in accepted if n in LOADER_FLAGS)
                 or "none of the input options")
        raise DofsplatError(f"{args.input}: {', '.join(wrong)} {verb} not apply to {what}; "
                            f"it takes {takes}")
    return given


def default_normalisation(path: Path) -> str:
    """What the loaders do without --normalise: "object" for points and meshes, "none" for
    a surfel or 3DGS PLY (taken as it is)."""
    from ..io.ply import ply_kind, read_ply_header

    ply = path.name.lower().endswith((".ply", ".ply.gz"))
    if ply and ply_kind(read_ply_header(path)) in ("surfels", "gaussians"):
        return "none (as stored)"
    return "object"


def sample_count(text: str):
    if text.strip().lower() == "vertices":
        return "vertices"
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number or 'vertices', got "
                                         f"{text!r}") from None
    if not 1 <= value <= MAX_MESH_SAMPLES:
        raise argparse.ArgumentTypeError(f"must be between 1 and {MAX_MESH_SAMPLES:,}, got "
                                         f"{text!r}")
    return value


def add_view_options(p: argparse.ArgumentParser, command: str) -> None:
    """The options that ``render``, ``demo`` and ``reference`` share; help texts name each
    one's defaults (``reference`` has ``render``'s, or the demo scene's with --demo)."""
    from ..demo import DEMO_APERTURE, DEMO_FOV_DEG

    is_demo = command == "demo"
    w, h = DEFAULT_SIZE.get(command, DEFAULT_SIZE["render"])
    demo_size = "; with --demo: {}x{}".format(*DEFAULT_SIZE["demo"]) if command == "reference" else ""

    out = p.add_argument_group("more outputs")
    out.add_argument("--depth", metavar="FILE",
                     help="also write the depth map: camera depth in world units, inf where "
                          "empty (.npy or .exr); .png gives a 16-bit picture of it, near is "
                          "dark, empty is black")
    out.add_argument("--stats", metavar="FILE.json",
                     help="also write statistics as JSON: points in, splats rendered, "
                          "fragments, milliseconds per stage and in total, and the camera, "
                          "lens and settings used")
    out.add_argument("-q", "--quiet", action="store_true",
                     help="do not print the summary line")

    cam = p.add_argument_group(
        "camera", "Where the camera is and what it sees. "
        + ("Default: the scene's camera." if is_demo else
           "Default: the model seen from its most visible side (of the four across the up "
           "axis: the one whose small pinhole render covers the most pixels; a Gaussian "
           "scene from +z, or from its trainer's first camera where a cameras.json is "
           "beside it; a depth capture from its sensor), from as near as keeps the whole "
           "model in the frame."))
    cam.add_argument("--size", metavar="WxH", type=image_size,
                     help=f"image size in pixels (default: {w}x{h}{demo_size})")
    cam.add_argument("--eye", nargs=3, type=finite_number, metavar=("X", "Y", "Z"),
                     help="camera position, world units")
    cam.add_argument("--target", nargs=3, type=finite_number, metavar=("X", "Y", "Z"),
                     help="point the camera looks at, world units"
                          + ("" if is_demo else " (default: the model's centre)"))
    cam.add_argument("--up", nargs=3, type=finite_number, metavar=("X", "Y", "Z"),
                     help="direction that appears upwards in the image (default: 0 1 0, or "
                          "0 0 1 for a point cloud whose ground faces +z)")
    view = cam.add_mutually_exclusive_group()
    view.add_argument("--fov", metavar="DEG", type=fov_degrees,
                      help="vertical field of view in degrees (default: "
                           + (f"{DEMO_FOV_DEG:g})" if is_demo else f"{DEFAULT_FOV_DEG:g})"))
    view.add_argument("--focal-length-mm", metavar="MM", type=positive_number,
                      help="a photographic lens of MM millimetres on a --sensor-width-mm "
                           "sensor: sets the field of view (the sensor's width over the "
                           "image's, the sensor at the image distance of the lens focused at "
                           "the focus distance, as dofsplat.photographic), and with "
                           "--f-number the lens diameter F / n. World units are taken as "
                           "metres (see --scene-scale); without --f-number the lens diameter "
                           "is the default one")
    view.add_argument("--frustum", nargs=5, type=finite_number, metavar=("L", "R", "B", "T", "N"),
                      help="the projection as glFrustum: the window [L, R] x [B, T] on the "
                           "near plane at distance N in front of the eye, world units; "
                           "(R-L)/(T-B) must equal W/H")

    lens = p.add_argument_group(
        "lens (depth of field)",
        "A thin lens: surfaces at the focus distance are sharp, nearer and farther ones blur "
        "the more, the wider the lens. Default: "
        + (f"the scene's lens, diameter {DEMO_APERTURE:g} world units, focused on the "
           "middle sphere."
           if is_demo else
           f"diameter {APERTURE_PER_HALF_DIAGONAL:g} x the half diagonal of the model's "
           "bounding box, focused on the surface at the image centre."))
    diameter = lens.add_mutually_exclusive_group()
    diameter.add_argument("--aperture", metavar="A", type=non_negative,
                          help="lens diameter, world units; 0 is a pinhole (all sharp)")
    diameter.add_argument("--f-number", metavar="N", type=positive_number,
                          help="f-number (f-stop) n, with --focal-length or "
                               "--focal-length-mm: the lens diameter is F / n, so a smaller n "
                               "blurs more")
    diameter.add_argument("--no-dof", action="store_true",
                          help="no depth of field: a pinhole camera, everything sharp")
    lens.add_argument("--focal-length", metavar="F", type=positive_number,
                      help="focal length F, world units (e.g. 0.05 for a 50 mm lens in a "
                           "model measured in metres); with --f-number it sets the lens "
                           "diameter, and the focus distance must exceed it. The field of "
                           "view is set by --fov or --frustum, not by F (--focal-length-mm "
                           "sets both)")
    lens.add_argument("--sensor-width-mm", metavar="MM", type=positive_number,
                      help=f"with --focal-length-mm: the sensor's width in millimetres "
                           f"(default: {DEFAULT_SENSOR_WIDTH_MM:g}, full frame; 23.5 is APS-C)")
    lens.add_argument("--scene-scale", metavar="M", type=positive_number,
                      help="with --focal-length-mm: the length of one world unit in metres "
                           "(default: 1; 0.001 for a model in millimetres), so that the lens "
                           "and its blur are those of the real camera at the model's size")
    lens.add_argument("--bokeh", choices=("disc", "gaussian"), default="disc",
                      help="the blur's shape: disc (default), the aperture's own image, flat "
                           "with a crisp edge as in a photograph; gaussian, the paper's soft "
                           "blob of the same size (docs/maths.md)")
    lens.add_argument("--blades", metavar="N", type=blade_count, default=0,
                      help="straight aperture blades, 5 to 16: defocused highlights become "
                           "N-gons (default 0: round)")
    lens.add_argument("--blade-rotation", metavar="DEG", type=finite_number, default=0.0,
                      help="turn the polygon of --blades by DEG degrees, counterclockwise")
    focus = lens.add_mutually_exclusive_group()
    focus.add_argument("--focus", metavar="P", type=positive_number,
                       help="focus distance, world units, measured along the view axis "
                            "(default: "
                            + ("the middle sphere; with --eye or --target, the distance "
                               "from eye to target)" if is_demo else
                               "the surface seen at the image centre, in a small pinhole "
                               "render, else the median depth of what it sees; with "
                               "--target, the distance from eye to target. The summary line "
                               "names the distance chosen)"))
    focus.add_argument("--focus-at", nargs=2, type=finite_number, metavar=("X", "Y"),
                       help="focus on the surface seen at pixel (X, Y), counted from the "
                            "top-left corner of the image (costs one extra, sharp render)")

    ren = p.add_argument_group("rendering")
    ren.add_argument("--cutoff", metavar="C", type=positive_number, default=DEFAULT_CUTOFF,
                     help="splat cutoff c: each Gaussian kernel is cut where its exponent "
                          f"reaches c; larger is smoother and slower (default: "
                          f"{DEFAULT_CUTOFF:g}, as in the paper)")
    ren.add_argument("--shading", choices=("phong", "none"),
                     help="phong: lit by a light at the camera; none: the surfel colours as "
                          "they are (default: phong; none for an RGB-D capture, whose colours "
                          "are photographs)")
    ren.add_argument("--background", nargs=3, type=unit_interval, metavar=("R", "G", "B"),
                     help="background colour, display (sRGB) values in 0..1 "
                          "(default: 0 0 0, black)")
    ren.add_argument("--no-cull", action="store_true",
                     help="keep surfels that face away from the camera and light both "
                          "sides (for models with inconsistent normals)")
    if command != "reference":
        ren.add_argument("--method", choices=("ours", "postfilter", "viewers"), default="ours",
                         help="ours: each splat blurred by its circle of confusion before "
                              "visibility (default); postfilter: the common post-process "
                              "baseline, a pinhole image blurred by the CoC of its depth "
                              "buffer (for comparison: it leaks intensity and misses partial "
                              "occlusion); viewers: for Gaussian scenes, the blur that splat "
                              "viewers ship (CoC^2 added to each footprint, its opacity "
                              "scaled), for comparison")
        ren.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu",
                         help="where to render: cpu (default); cuda, an NVIDIA GPU (pip install "
                              "'dofsplat[cuda]'; an error if none works); auto, the GPU if one "
                              "works, else the CPU")

    if command == "reference":
        return  # its lens samples are full-resolution pinhole renders: no LOD options
    p.add_argument("--reconstruction", choices=("soft", "paper"), default="soft",
                   help="how blurred surfaces meet: soft (default) merges surfaces whose "
                        "parallax is small against their blur and removes what such a "
                        "surface hides, so a blurred object touching another shows no seam; "
                        "paper is Section 6.4's z-range decision alone (docs/maths.md)")
    p.add_argument("--sharp-visibility", action="store_true",
                   help="in a sharp frame (no lens, or --no-dof) too, remove the surfels "
                        "hidden behind an opaque surface before blending, so that a surface "
                        "seen at a grazing angle does not let what lies just behind it show "
                        "through (speckle where two surfaces cross at a shallow angle); "
                        "1.1-1.5x a sharp frame's time. Blurred frames always do it, and the "
                        "reference's samples and --method postfilter's sharp frame too")
    p.add_argument("--lens-samples", metavar="K", type=lens_sample_count, default=1,
                   help="draw the aperture as K parts (1-64), each a frame seen from its own "
                        "point of the lens with the rest of the blur, averaged: where blurred "
                        "surfaces touch or overlap, visibility is decided K times over a "
                        "smaller blur (4: 0.7-4.8 dB closer to the reference than one pass, "
                        "ahead of the post-filter on every frame of the fidelity suite, for "
                        "6-10x a pinhole frame at a 40-pixel blur). An isolated bright point "
                        "then shows K lobes instead of the aperture's disc or polygon, so the "
                        "default is 1, the paper's single pass (docs/maths.md, \"the lens in "
                        "parts\")")
    p.add_argument("--lens-parts", choices=("everywhere", "needed"), default="everywhere",
                   help="with --lens-samples K > 1: draw the parts everywhere, or only where "
                        "a pixel's A-buffer held two surfaces or more (and beside them), "
                        "over one pass of the whole lens elsewhere (CPU; the GPU draws them "
                        "everywhere). On the fidelity suite it scores within 1.5 dB of the "
                        "parts everywhere on 16 of 18 frames and draws single surfaces and "
                        "lone points with the aperture's own shape, but costs as much or more (bench/RESULTS.md, \"The lens in "
                        "parts where needed\")")
    p.add_argument("--coarse-blur", metavar="PX", type=non_negative,
                   default=RenderSettings.coarse_blur_px,
                   help="a splat blurred by an aperture of at least PX pixels' radius is drawn "
                        "at every second pixel and interpolated (default 8: blurred frames "
                        "0.62-0.87x their time, within 65 dB of every pixel, 0-0.4 dB further "
                        "from the reference; 0 draws every pixel; docs/maths.md, \"Wide blurs "
                        "at every second pixel\")")
    lod = p.add_argument_group(
        "level of detail",
        "Blurred surfaces are drawn from a coarser level of a hierarchy over the surfels, "
        "so the time per frame hardly depends on the aperture (the paper's Section 6.2). "
        "The picture stays the same (PSNR against --no-lod: 64-78 dB on the plane of the "
        "paper's Table 1, 54-63 dB on its lion scan; python bench/table1.py).")
    lod.add_argument("--lod", action=argparse.BooleanOptionalAction, default=True,
                     help="select splats from the hierarchy (default: on); --no-lod splats "
                          "every surfel")
    lod.add_argument("--lod-threshold", metavar="PX", type=non_negative, default=1.0,
                     help="also draw a node whole when its disk projects to at most PX "
                          "pixels in radius, as QSplat does (default: 1; 0 keeps every "
                          "surfel that the blur does not merge)")
    lod.add_argument("--lod-blur-fraction", metavar="K", type=fraction,
                     default=RenderSettings.lod_blur_fraction,
                     help="draw a node when its own blur is at most K times the depth-of-"
                          "field blur (variance): 0.35 (default) keeps textures and contacts "
                          "close to the exact picture (0-3.6 dB from --no-lod on the fidelity "
                          "suite, 0.5-10 dB at 1) for 1.3-3.2x a pinhole frame at a 40-pixel "
                          "blur; 1 (with --lod-min-node 2) is the paper's rule, faster and "
                          "softer")
    lod.add_argument("--lod-color-tolerance", metavar="T", type=tolerance,
                     default=RenderSettings.lod_color_tolerance,
                     help="draw a node finer where it has more texture at its own scale "
                          "than T (RMS, linear RGB; what its colour ramp cannot draw): "
                          "down to 0.3 x K (default: 0.02; 'inf' turns it off). Keeps "
                          "checkers and textures within 1 dB of --no-lod on the fidelity "
                          "suite")
    lod.add_argument("--lod-min-node", metavar="M", type=min_node_count,
                     default=RenderSettings.lod_min_node,
                     help="the blur draws only nodes of at least M surfels; smaller ones "
                          "are drawn as their surfels (default: 4, which brings the crossing "
                          "planes and the lion's leaves of the fidelity suite within 1 dB of "
                          "--no-lod at 10 and 20 px of blur, for 1.1-1.4x the fragments and "
                          "1.0-1.4x the time of 2; 2 draws any node, as the paper does; "
                          "docs/maths.md, \"The smallest nodes\")")
    lod.add_argument("--show-lod", action="store_true",
                     help="colour each splat by its level (grey: single surfels, then "
                          "blue, cyan, green, ... as nodes get coarser) and draw it without "
                          "the blur, to see which levels the depth of field selects")
    lod.add_argument("--taper", action="store_true",
                     help="with --bokeh gaussian: taper LOD nodes' Gaussians to 0 at the "
                          "cutoff, so that very large blurs show no hard-edged discs; it "
                          "also narrows them, so it is off by default (docs/maths.md). The "
                          "aperture's kernels (the default) are always tapered")
    if not is_demo:
        lod.add_argument("--lod-cache", metavar="FILE|auto|off", default="auto",
                         help="where the hierarchy is kept between runs: auto (default) "
                              "in ~/.cache/dofsplat/lod; a FILE.npz, e.g. next to the "
                              "model; off builds it each time. A changed model is detected "
                              "and its hierarchy rebuilt")


# -- argument types --------------------------------------------------------------------


def blade_count(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of blades, got {text!r}") from None
    if n != 0 and not 5 <= n <= 16:
        raise argparse.ArgumentTypeError(f"blades must be 0 (round) or 5 to 16, got {n}")
    return n


def image_size(text: str) -> tuple[int, int]:
    # signs are read, so that -320x240 is told it is too small, not that it is not WxH
    m = re.fullmatch(r"\s*([-+]?\d+)\s*[xX]\s*([-+]?\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels such as 640x480, "
                                         f"got {text!r}")
    width, height = int(m[1]), int(m[2])
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"the image needs at least 1x1 pixels, got {text!r}")
    return width, height


def finite_number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_number(text: str) -> float:
    value = finite_number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def whole_number(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def lens_sample_count(text: str) -> int:
    """--lens-samples: an integer in 1..MAX_LENS_SAMPLES."""
    k = whole_number(text)
    if not 1 <= k <= MAX_LENS_SAMPLES:
        raise argparse.ArgumentTypeError(f"lens samples must be 1..{MAX_LENS_SAMPLES}, got {k}")
    return k


def min_node_count(text: str) -> int:
    """--lod-min-node: an integer in 2..MAX_LOD_MIN_NODE."""
    m = whole_number(text)
    if not 2 <= m <= MAX_LOD_MIN_NODE:
        raise argparse.ArgumentTypeError(f"the smallest node must be 2..{MAX_LOD_MIN_NODE} "
                                         f"surfels, got {m}")
    return m


# prep.pointcloud's MIN_K and MAX_K and prep.meshes' MAX_SAMPLES, written out: importing
# them here would load numba and scipy while the arguments are parsed (tests/test_cli.py
# checks that they agree)
MIN_NEIGHBOURS, MAX_NEIGHBOURS = 4, 256
MAX_MESH_SAMPLES = 50_000_000


def neighbour_count(text: str) -> int:
    value = whole_number(text)
    if not MIN_NEIGHBOURS <= value <= MAX_NEIGHBOURS:
        raise argparse.ArgumentTypeError(f"must be from {MIN_NEIGHBOURS} to {MAX_NEIGHBOURS} "
                                         f"neighbours, got {text!r}")
    return value


def positive_int(text: str) -> int:
    value = whole_number(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return value


def non_negative(text: str) -> float:
    value = finite_number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


def tolerance(text: str) -> float:
    """A number >= 0, or 'inf' (off)."""
    if text.strip().lower() in ("inf", "off"):
        return float("inf")
    return non_negative(text)


def fraction(text: str) -> float:
    value = finite_number(text)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1], got {text!r}")
    return value


def unit_interval(text: str) -> float:
    value = finite_number(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in 0..1, got {text!r}")
    return value


def fov_degrees(text: str) -> float:
    value = finite_number(text)
    if not 0.0 < value < 180.0:
        raise argparse.ArgumentTypeError(f"must be between 0 and 180 degrees, got {text!r}")
    return value
