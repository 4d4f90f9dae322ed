"""The README's commands run as written (issue 18): every ``dofsplat`` command of its bash
blocks and of its tables, from the project root's place (a scratch folder beside the shared
models, so that ``../shared/data/...`` resolves as from the project root), with
``model.ply`` a small surfel model of our own. Files that stand for the user's own
(``surfels.ply``, ``part.stl``, ``site.e57``) are skipped. Two substitutions keep the suite
quick without changing what a command checks (its paths and options): a ``reference``
without ``--samples`` takes 8 lens samples instead of 200, and ``--device cuda`` is skipped
where no GPU works (it is a clear error there)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from dofsplat import cli
from dofsplat.io import save_surfels
from dofsplat.surfels import Surfels

from conftest import SHARED_DATA

README = Path(__file__).resolve().parents[1] / "README.md"
MODEL_EXT = re.compile(r"\.(ply|ply\.gz|obj|gltf|glb|stl|off|las|laz|e57|pcd)$", re.I)


def readme_commands() -> list[str]:
    """Every dofsplat command line of the README: bash blocks first, then inline code."""
    text = README.read_text(encoding="utf-8")
    out = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #")[0].strip()
            if line.startswith("dofsplat "):
                out.append(line)
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    out += [c for c in re.findall(r"`(dofsplat (?:render|demo|reference|convert)[^`]*)`", prose)
            if c not in out and not re.search(r"[A-Z]{3,}", c)  # no FILE placeholders
            and (len(c.split()) > 2 or c == "dofsplat demo")]  # not a command's mere name
    return out


def test_the_readme_has_commands():
    commands = readme_commands()
    assert len(commands) >= 30
    assert any("../shared/data/lion_takanawa/" in c for c in commands)


@pytest.fixture(scope="module")
def project_root(tmp_path_factory):
    """A scratch folder standing where the project root stands (../shared/data beside it
    by a link), holding model.ply: a small square of surfels facing +z."""
    base = tmp_path_factory.mktemp("readme")
    (base / "shared").symlink_to(SHARED_DATA.parent, target_is_directory=True)
    root = base / "project"
    root.mkdir()
    (root / "docs").symlink_to(README.parent / "docs", target_is_directory=True)  # docs/moves.json
    g = (np.arange(48) + 0.5) / 48 * 2 - 1
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    n = x.size
    save_surfels(root / "model.ply", Surfels(
        positions=np.stack([x, y, np.zeros(n)], 1), normals=np.tile([0.0, 0.0, 1.0], (n, 1)),
        radius=np.full(n, 2 / 48), colors=np.stack([0.5 + x / 2, 0.5 + y / 2, 0.5 + 0 * x], 1)))
    return root


@pytest.mark.parametrize("line", readme_commands(), ids=[c[9:70] for c in readme_commands()])
def test_readme_command_runs(line, project_root, monkeypatch, capsys):
    args = shlex.split(line)[1:]
    if "--device" in args and args[args.index("--device") + 1] == "cuda":
        from dofsplat.backends import cuda_problem

        if cuda_problem() is not None:
            pytest.skip(f"no CUDA GPU here: {cuda_problem()}")
    if any("../shared/data" in a for a in args) and not SHARED_DATA.is_dir():
        pytest.skip(f"the shared models are not at {SHARED_DATA}")
    inputs = [a for a in args[1:2] if MODEL_EXT.search(a)] if args[0] != "compare" else []
    if inputs and not (project_root / inputs[0]).exists():
        pytest.skip(f"{inputs[0]} stands for a file of the user's own")
    if args[0] == "reference" and "--samples" not in args:
        args += ["--samples", "8"]
    monkeypatch.setenv("DOFSPLAT_CACHE_MAX", "1G")  # each shared model is prepared once
    monkeypatch.chdir(project_root)
    status = cli.main(args if args[0] == "cache" else args + ["-q"])
    err = capsys.readouterr().err
    assert status == 0, f"{line}: {err}"
