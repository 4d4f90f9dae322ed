"""A small, repeatable mutation check of the kernels (issue 52): does a wrong kernel fail a test?

Each mutant is one operator or constant changed in one file of dofsplat/raster/, splat/,
lod/ or sequence.py: a (file, exact old text, new text) triple, the old text found exactly
once. For each, the repository is copied to a temporary folder (the same folder each time),
the change applied there, and the mutant's covering tests run on the copy (``pytest -x
-q``, PYTHONPATH pointing at the copy) with a numba kernel cache of its own
(DOFSPLAT_KERNEL_DIR, ``dofsplat/jit.py``). A mutant is killed when a test fails.

The kernel cache: numba keeps a kernel's machine code keyed by its own source file's
stamp, and a kernel that calls (inlines) a function of another module keeps that code
too, unchecked. So a mutant's cache must hold nothing compiled from the changed module or
from any module that imports it, directly or not. By default it starts as a copy of a
cache compiled once from the unchanged copy (``seed``), less every module that imports the
changed one: the kernels that could have changed compile again, the rest are loaded (a
mutant in abuffer.py compiles abuffer's kernels alone; one in ewa.py compiles them all,
285 s on two busy cores). ``--fresh`` starts every mutant from an empty cache.

    python bench/mutants.py --list            # the mutants, numbered
    python bench/mutants.py                   # all of them (about 1-5 minutes each)
    python bench/mutants.py --only 3,17       # some
    python bench/mutants.py --json out.json   # and the results as JSON
    python bench/mutants.py --table a.json b.json   # earlier runs as a Markdown table

It prints one line per mutant (killed, by which test; or SURVIVED) and the count.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
WORK = Path(tempfile.gettempdir()) / "dofsplat-mutants"
TIMEOUT_S = 1500  # a mutant whose tests run longer is reported as a timeout (not killed)


@dataclass(frozen=True)
class Mutant:
    file: str  # relative to the repository
    old: str  # exact text, found once
    new: str
    tests: tuple  # pytest arguments: files, node ids, -k expressions
    what: str  # the change, in words


TWINS = ("tests/test_render.py", "-k", "twin")
RECON = "tests/test_reconstruction.py"
BOKEH = "tests/test_bokeh.py"
LOD = "tests/test_lod.py"

MUTANTS = [
    # -- raster/abuffer.py: the A-buffer, the front pass, the resolve ----------------------
    Mutant("dofsplat/raster/abuffer.py", "MERGE_REACH = 6.0", "MERGE_REACH = 2.0", TWINS,
           "the front's reach behind it, 6 -> 2 (CoC + 1) |g|"),
    Mutant("dofsplat/raster/abuffer.py", "OPAQUE = 0.95", "OPAQUE = 0.5", TWINS,
           "the opacity from which a fragment hides what is behind it, 0.95 -> 0.5"),
    Mutant("dofsplat/raster/abuffer.py", "\nCOVER_FULL = 0.9\n", "\nCOVER_FULL = 0.99\n",
           (RECON, "-k", "cover_full"), "a sharp surface's full coverage from 0.9 -> 0.99"),
    Mutant("dofsplat/raster/abuffer.py", "HIDDEN_H0 = 0.9", "HIDDEN_H0 = 0.5", TWINS,
           "the hidden share from which a splat is removed, 0.9 -> 0.5"),
    Mutant("dofsplat/raster/abuffer.py", "LENS_MARGIN = 2.0", "LENS_MARGIN = 0.0", TWINS,
           "the looks through the lens without their 2 px margin"),
    Mutant("dofsplat/raster/abuffer.py", "FRONT_CUTOFF = 2.0", "FRONT_CUTOFF = 0.5", TWINS,
           "the front pass's disks a quarter as large"),
    Mutant("dofsplat/raster/abuffer.py", "    acc[p, hit, S_WA] += w * a\n",
           "    acc[p, hit, S_WA] += w\n", TWINS,
           "a merged fragment's opacity taken as 1"),
    Mutant("dofsplat/raster/abuffer.py",
           "    acc[p, i, S_ZHI] = max(acc[p, i, S_ZHI], acc[p, j, S_ZHI])",
           "    acc[p, i, S_ZHI] = min(acc[p, i, S_ZHI], acc[p, j, S_ZHI])",
           (*TWINS, LOD, "-k", "twin or full_abuffer"),
           "two surfaces merged keep the nearer far end"),
    Mutant("dofsplat/raster/abuffer.py", "    return (1.0 - t * t * (3.0 - 2.0 * t)) * o",
           "    return (1.0 - t) * o", (RECON, "-k", "merge_fraction or partitions"),
           "the merge band linear instead of smoothstep"),
    Mutant("dofsplat/raster/abuffer.py",
           "    rho = (coc_k * abs(1.0 / d_front - 1.0 / d_back) + 1.0) / c",
           "    rho = (coc_k * abs(1.0 / d_front - 1.0 / d_back) + 0.0) / c",
           (RECON, "-k", "merge_fraction or partitions"),
           "the merge ratio without its 1 px"),
    Mutant("dofsplat/raster/abuffer.py", "    return max(min(1.0, w) * wa / w, cover)",
           "    return min(1.0, w) * wa / w", (RECON, "-k", "cover"),
           "a surface's opacity without its opaque coverage"),
    Mutant("dofsplat/raster/abuffer.py",
           "    return min(max(2.0 - coc_radius_px(d, coc_k, inv_focus) / COVER_SHARP_PX, 0.0), 1.0)",
           "    return min(max(1.0 - coc_radius_px(d, coc_k, inv_focus) / COVER_SHARP_PX, 0.0), 1.0)",
           TWINS, "sharpness fading from 0 px instead of COVER_SHARP_PX"),
    Mutant("dofsplat/raster/abuffer.py",
           "    zlo, depth = splats[k, ZLO] - 0.75 * grad, splats[k, DEPTH]",
           "    zlo, depth = splats[k, ZLO] - 0.0 * grad, splats[k, DEPTH]",
           (RECON, "-k", "visibility"), "the visibility without its 0.75 px depth slack"),
    Mutant("dofsplat/raster/abuffer.py", "                if d < front[p, 0]:",
           "                if d <= front[p, 0]:", TWINS,
           "the front map's nearest disk: ties go to the later splat (an equivalent mutant?)"),
    Mutant("dofsplat/raster/abuffer.py",
           "                ft += end * (1.0 - alpha) * scratch[nxt + 3]",
           "                ft += end * scratch[nxt + 3]", (RECON, "-k", "partitions"),
           "the resolve's transmittance not reduced by a run's alpha"),
    Mutant("dofsplat/raster/abuffer.py", "        cx = width - 0.5", "        cx = width - 1.5",
           (RECON, "-k", "beyond_the_frame or visibility"),
           "the front read at the last-but-one column beyond the right edge"),
    Mutant("dofsplat/raster/abuffer.py",
           "overflows += insert_fragment(acc, cnt, p, amp * (e - floor), max(rr, 0.0),",
           "overflows += insert_fragment(acc, cnt, p, amp * e, max(rr, 0.0),",
           ("tests/test_render.py", LOD, "-k", "twin or tapered or taper"),
           "a tapered kernel drawn without its floor"),
    # -- splat/ewa.py: the per-splat maths -------------------------------------------------
    Mutant("dofsplat/splat/ewa.py", "SMALL_APERTURE = 1.0", "SMALL_APERTURE = 4.0", TWINS,
           "apertures up to 4 sigma drawn as a Gaussian"),
    Mutant("dofsplat/splat/ewa.py", "            w11 += 0.25 * radius * radius",
           "            w11 += 0.5 * radius * radius", TWINS,
           "a small aperture's moment-matched Gaussian twice as wide along x"),
    Mutant("dofsplat/splat/ewa.py", "DOF_VARIANCE_FACTOR = 1.0 / (2.0 * LN4)",
           "DOF_VARIANCE_FACTOR = 1.0 / LN4",
           ("tests/test_kernel.py", "tests/test_render.py", "-k", "twin or dof_factor or out_of_focus"),
           "the paper's DOF variance doubled (Section 5.2)"),
    Mutant("dofsplat/splat/ewa.py", "        elif depth * inv_focus < 1.0:",
           "        elif depth * inv_focus > 1.0:", (BOKEH, "-k", "turns_over", *TWINS[:1]),
           "the aperture turned over behind the focal plane instead of before"),
    Mutant("dofsplat/splat/ewa.py",
           "    half = reach * math.sqrt(var_z) + z_margin * 2.0 * sigma_l",
           "    half = reach * math.sqrt(var_z) + z_margin * 0.5 * sigma_l", TWINS,
           "the z-range's thickness a quarter"),
    Mutant("dofsplat/splat/ewa.py", "    su, sv = 0.5 * ru, 0.5 * rv",
           "    su, sv = 0.5 * ru, 0.5 * ru", TWINS, "an elliptical surfel drawn round"),
    Mutant("dofsplat/splat/ewa.py", "        w11 = b11 + q11 / 3.0 + e11",
           "        w11 = b11 + q11 / 2.0 + e11", (LOD, "-k", "twin"),
           "a node's spread Q/3 taken as Q/2 along x"),
    # -- splat/bokeh.py: the aperture's kernel ---------------------------------------------
    Mutant("dofsplat/splat/bokeh.py", "        table = np.clip(t - s * t[:, -1:], 0.0, None)",
           "        table = np.clip(t, 0.0, None)", TWINS, "the aperture table without its taper"),
    Mutant("dofsplat/splat/bokeh.py", "    return radius * math.cos(math.pi / n) / best",
           "    return radius / best", (BOKEH, "-k", "hexagon or turns_over"),
           "a polygon's radius from its circumradius, not its inradius"),
    Mutant("dofsplat/splat/bokeh.py", "        s = s_gauss + m * (s_edge - s_gauss)",
           "        s = s_gauss", (BOKEH, "-k", "simd"),
           "the SIMD rows' scale without the edge's share"),
    Mutant("dofsplat/splat/bokeh.py", "    return r2 / (r2 + 0.5 * (w11 + w22))",
           "    return r2 / (r2 + (w11 + w22))", TWINS, "the edge mix from twice the variance"),
    Mutant("dofsplat/splat/bokeh.py", "    g1 = r + u_c * s1\n", "    g1 = r + 0.5 * u_c * s1\n",
           (BOKEH, "-k", "support"), "the support's ellipse too small"),
    Mutant("dofsplat/splat/bokeh.py", "B_MAX = 8.0", "B_MAX = 6.0", TWINS,
           "the aperture table's b range 0..6"),
    # -- lod/: the cut -----------------------------------------------------------------------
    Mutant("dofsplat/lod/select.py",
           "        margin = math.sqrt(2.0 * cutoff * (dof_variance(coc_max) + 1.0)) + 1.0",
           "        margin = math.sqrt(2.0 * cutoff * (0.0 + 1.0)) + 1.0",
           (LOD, "-k", "frustum"), "the frustum's margin without the blur (issue 52, item 5)"),
    Mutant("dofsplat/lod/select.py",
           "        coc_min = min(coc_radius_px(u_lo, coc_k, inv_focus), coc_radius_px(u_hi, coc_k, inv_focus))",
           "        coc_min = max(coc_radius_px(u_lo, coc_k, inv_focus), coc_radius_px(u_hi, coc_k, inv_focus))",
           (LOD, "-k", "quality or stop or crossing"),
           "the DOF stop by the largest CoC over the node, not the smallest"),
    Mutant("dofsplat/lod/select.py",
           "            return DESCEND  # the focal plane runs through the node",
           "            return SELECT  # the focal plane runs through the node",
           (LOD, "-k", "quality or stop or crossing"),
           "a node the focal plane runs through drawn whole"),
    Mutant("dofsplat/lod/select.py",
           "        if 4.0 * (np.float64(sigma_r2[r]) * lam_j + lam_q) <= thr2:",
           "        if 4.0 * lam_q <= thr2:", (LOD, "-k", "pinhole or valid_coarsest"),
           "the pixel stop without the node's own disk"),
    Mutant("dofsplat/lod/hierarchy.py",
           "    c3 = fl * (L[V_COV + 3] + d1l * d1l) + fr * (R[V_COV + 3] + d1r * d1r)",
           "    c3 = fl * L[V_COV + 3] + fr * R[V_COV + 3]",
           (LOD, "-k", "prefiltered or node_filter"),
           "a node's covariance without the parallel-axis term along y"),
    # -- sequence.py: frames of a sequence -------------------------------------------------
    Mutant("dofsplat/sequence.py", "    return u * u * (3.0 - 2.0 * u) if easing == \"smooth\" else u",
           "    return u * (3.0 - 2.0 * u) if easing == \"smooth\" else u",
           ("tests/test_animate.py", "-k", "interpolation"), "the easing not smoothstep"),
    Mutant("dofsplat/sequence.py",
           "        t = k / (n_frames - 1) if n_frames > 1 else 0.0",
           "        t = k / n_frames if n_frames > 1 else 0.0",
           ("tests/test_animate.py", "-k", "single_render or cli_frame or decode"),
           "the last frame short of the last keyframe"),
    Mutant("dofsplat/sequence.py", "\"model\": content_hash(surfels),",
           "\"model\": str(len(surfels)),",
           ("tests/test_animate.py", "-k", "another_model or edited"),
           "the model's fingerprint its surfel count (issue 52, item 1)"),
]


# -- the run -------------------------------------------------------------------------------


def kernel_modules(package: Path) -> dict[str, set[str]]:
    """{module stem path "splat/ewa": the module stem paths it imports from the package},
    read from every ``from .x import`` / ``from ..x.y import`` in its source (anywhere in
    the file: a function's own imports count)."""
    graph = {}
    for path in package.rglob("*.py"):
        rel = path.relative_to(package).with_suffix("")
        here = list(rel.parts[:-1])
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level > 0:
                base = here[:len(here) - (node.level - 1)] if node.level > 1 else here
                target = base + (node.module.split(".") if node.module else [])
                deps.add("/".join(target))
                for alias in node.names:  # "from . import ewa": a module too
                    deps.add("/".join(target + [alias.name]))
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dofsplat."):
                deps.add("/".join(node.module.split(".")[1:]))
        graph["/".join(rel.parts)] = deps
    return graph


def dependents(graph: dict[str, set[str]], module: str) -> set[str]:
    """``module`` and every module that imports it, directly or through others."""
    out, todo = {module}, [module]
    while todo:
        m = todo.pop()
        for k, deps in graph.items():
            if k not in out and (m in deps or m + "/__init__" in deps):
                out.add(k)
                todo.append(k)
    return out


def seed_without(seed: Path, kernels: Path, stale: set[str]) -> None:
    """Copy the compiled kernels of ``seed`` into ``kernels``, less those of the modules in
    ``stale`` (numba names a folder per source folder, "<folder>_<hash>", and a file per
    kernel, "<module>.<function>-<line>.py<ver>...")."""
    kernels.mkdir(parents=True)
    drop = {(Path(m).parent.name or "dofsplat", Path(m).name) for m in stale}
    for folder in seed.iterdir():
        if not folder.is_dir():
            continue
        src_dir = folder.name.rsplit("_", 1)[0]
        (kernels / folder.name).mkdir()
        for f in folder.iterdir():
            if (src_dir, f.name.split(".", 1)[0]) not in drop:
                shutil.copy2(f, kernels / folder.name / f.name)


def copy_repo(dest: Path) -> None:
    """The repository's working tree at ``dest`` (modification times kept: numba's cache
    index compares them), without .git and caches."""
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(REPO, dest, symlinks=True,
                    ignore=shutil.ignore_patterns(".git", "__pycache__", ".pytest_cache",
                                                  "*.egg-info", ".venv", "node_modules"))


def environment(copy: Path, kernels: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(copy), DOFSPLAT_KERNEL_DIR=str(kernels),
               NUMBA_NUM_THREADS=os.environ.get("NUMBA_NUM_THREADS", "2"),
               PYTHONDONTWRITEBYTECODE="1")
    env.pop("NUMBA_DISABLE_JIT", None)
    return env


def kernel_stamps(copy: Path) -> dict:
    """(mtime, size) of every source file of the package that jits a kernel: the seed is
    valid while they hold (an edit elsewhere, say to the command line, leaves it valid)."""
    return {str(p.relative_to(copy)): [p.stat().st_mtime, p.stat().st_size]
            for p in sorted((copy / "dofsplat").rglob("*.py"))
            if re.search(r"njit|numba\.jit|cuda\.jit|@shared", p.read_text(encoding="utf-8"))}


def compile_seed(copy: Path, seed: Path, log) -> None:
    if seed.exists():
        shutil.rmtree(seed)
    seed.mkdir(parents=True)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", "from dofsplat.render import warm_up; warm_up()"],
                          cwd=copy, env=environment(copy, seed), capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"the unchanged copy does not compile:\n{done.stderr[-3000:]}")
    log(f"seed: compiled the unchanged kernels in {time.perf_counter() - t0:.0f} s")


def run_mutant(index: int, m: Mutant, fresh: bool, graph, state: dict, log) -> dict:
    copy, seed = WORK / "repo", WORK / "seed"
    copy_repo(copy)
    stamps = kernel_stamps(copy)
    kept = seed / "stamps.json"  # the stamps the seed was compiled from (a rerun reuses it)
    if not fresh and "stamps" not in state and kept.exists():
        state["stamps"] = json.loads(kept.read_text())
    if not fresh and state.get("stamps") != stamps:  # first use, or the kernels changed
        compile_seed(copy, seed, log)
        state["stamps"] = stamps
        kept.write_text(json.dumps(stamps))
    target = copy / m.file
    text = target.read_text(encoding="utf-8")
    found = text.count(m.old)
    if found != 1:
        return {"index": index, "result": "stale", "detail": f"old text found {found} times"}
    target.write_text(text.replace(m.old, m.new), encoding="utf-8")
    kernels = WORK / f"kernels-{index}"
    if kernels.exists():
        shutil.rmtree(kernels)
    module = str(Path(m.file).relative_to("dofsplat").with_suffix(""))
    if fresh:
        kernels.mkdir(parents=True)
    else:
        seed_without(seed, kernels, dependents(graph, module))
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *m.tests]
    try:
        done = subprocess.run(cmd, cwd=copy, env=environment(copy, kernels),
                              capture_output=True, text=True, timeout=TIMEOUT_S)
        rc, out = done.returncode, done.stdout + done.stderr
    except subprocess.TimeoutExpired as e:
        rc, out = None, (e.stdout or b"").decode(errors="replace") if isinstance(e.stdout, bytes) \
            else (e.stdout or "")
    seconds = time.perf_counter() - t0
    shutil.rmtree(kernels, ignore_errors=True)
    failed = re.findall(r"^(?:FAILED|ERROR) (\S+)", out, re.M)
    summary = (out.strip().splitlines() or [""])[-1]
    if rc is None:
        result = "timeout"
    elif rc == 0:
        result = "survived"
    elif rc == 1:
        result = "killed"
    elif rc == 5:
        result = "no tests"  # the mutant's test selection matched nothing: fix the list
    else:
        result = "error"  # collection or usage error: read the log
    return {"index": index, "file": m.file, "what": m.what, "result": result,
            "by": failed[0] if failed else "", "seconds": round(seconds, 1),
            "summary": summary, "tests": " ".join(m.tests),
            "tail": out[-1500:] if result in ("error", "no tests") else ""}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--list", action="store_true", help="list the mutants and exit")
    ap.add_argument("--only", help="comma-separated mutant numbers (from --list)")
    ap.add_argument("--fresh", action="store_true",
                    help="every mutant from an empty kernel cache (no seed)")
    ap.add_argument("--json", help="write the results to this file")
    ap.add_argument("--table", nargs="+", metavar="JSON",
                    help="print the results of earlier runs (--json files) as a Markdown "
                         "table for bench/RESULTS.md, and exit")
    args = ap.parse_args(argv)
    if args.table:
        rows = {}
        for f in args.table:
            for r in json.loads(Path(f).read_text()):
                rows[r["index"]] = r  # a later file's result replaces an earlier one's
        print("| # | file | change | result | killed by | s |\n|---|---|---|---|---|---|")
        for i in sorted(rows):
            r = rows[i]
            print(f"| {i} | {MUTANTS[i].file.removeprefix('dofsplat/')} | {MUTANTS[i].what} "
                  f"| {r['result']} | {r.get('by', '').replace('tests/', '')} "
                  f"| {r.get('seconds', '')} |")
        counted = [r for r in rows.values() if r["result"] in ("killed", "survived", "timeout")]
        killed = sum(r["result"] == "killed" for r in counted)
        print(f"\nkilled {killed} of {len(counted)}")
        return 0
    if args.list:
        for i, m in enumerate(MUTANTS):
            print(f"{i:3d}  {m.file}: {m.what}\n       {m.old.strip()!r} -> {m.new.strip()!r}"
                  f"\n       tests: {' '.join(m.tests)}")
        return 0
    chosen = range(len(MUTANTS)) if not args.only else [int(x) for x in args.only.split(",")]

    def log(line):
        print(line, flush=True)

    WORK.mkdir(parents=True, exist_ok=True)
    graph = kernel_modules(REPO / "dofsplat")
    state, results = {}, []
    t0 = time.perf_counter()
    for i in chosen:
        r = run_mutant(i, MUTANTS[i], args.fresh, graph, state, log)
        results.append(r)
        by = f" by {r['by']}" if r.get("by") else ""
        log(f"{i:3d} {r['result'].upper():9s} {r.get('seconds', 0):6.0f} s  "
            f"{MUTANTS[i].file}: {MUTANTS[i].what}{by}")
        if r.get("tail"):
            log(r["tail"])
        if args.json:
            Path(args.json).write_text(json.dumps(results, indent=1) + "\n")
    counted = [r for r in results if r["result"] in ("killed", "survived", "timeout")]
    killed = sum(r["result"] == "killed" for r in counted)
    log(f"killed {killed} of {len(counted)} ({100 * killed / max(len(counted), 1):.0f} %) "
        f"in {(time.perf_counter() - t0) / 60:.0f} min; survived: "
        + (", ".join(str(r["index"]) for r in counted if r["result"] != "killed") or "none"))
    other = [r for r in results if r not in counted]
    if other:
        log("not run: " + ", ".join(f"{r['index']} ({r['result']})" for r in other))
    return 0


if __name__ == "__main__":
    sys.exit(main())
