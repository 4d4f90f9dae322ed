"""The README's two set-up commands, run in order in one fresh environment (issue 51).

The first (``pip install . && dofsplat demo``) installed a regular copy, and numba wrote its
compiled kernels beside that copy's sources in site-packages; the second (``pip install -e
".[test]"``) removed the copy but not those files, so the package's folders stayed, holding
only ``__pycache__``, and Python took ``site-packages/dofsplat/splat`` for a namespace
package: ``dofsplat demo`` failed with ``No module named 'dofsplat.splat.subaperture'``.
CI runs only the second command in a fresh clone, so only this test sees it.

Slow (two installs and one cold compile of every kernel: about 3 minutes on 2 cores), and it
needs the package index for the build's setuptools; ``DOFSPLAT_SKIP_INSTALL_TEST=1`` skips it.
The second install is of this checkout itself (editable, into the test's own environment:
the checkout's installs elsewhere are untouched).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def readme_setup_commands() -> tuple[str, str]:
    """The README's first code block: (the install-and-demo line, the install-and-test line),
    without their comments."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", text, re.S)[1]
    lines = [ln.split("#")[0].strip() for ln in block.splitlines() if ln.strip()]
    demo = next(ln for ln in lines if "dofsplat demo" in ln)
    tests = next(ln for ln in lines if "pytest" in ln or ".[test]" in ln)
    return demo, tests


def install_part(command: str) -> str:
    """The install step of the test line: what comes before its first ``&&``."""
    return command.split("&&")[0].strip()


def kernel_files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.suffix in (".nbi", ".nbc")]


def run(command: str, cwd: Path, env: dict) -> subprocess.CompletedProcess:
    result = subprocess.run(command, shell=True, cwd=cwd, env=env, capture_output=True,
                            text=True, timeout=900, stdin=subprocess.DEVNULL)
    assert result.returncode == 0, (f"{command!r} in {cwd} exited {result.returncode}:\n"
                                    f"{result.stdout[-2000:]}\n{result.stderr[-3000:]}")
    return result


@pytest.mark.skipif(os.environ.get("DOFSPLAT_SKIP_INSTALL_TEST") == "1",
                    reason="DOFSPLAT_SKIP_INSTALL_TEST=1")
def test_readme_commands_in_order_then_demo_from_another_folder(tmp_path):
    demo_line, test_line = readme_setup_commands()
    assert demo_line.startswith("python3 -m pip install . && dofsplat demo"), demo_line
    assert install_part(test_line) == 'python3 -m pip install -e ".[test]"', test_line

    # one fresh environment; the dependencies come from this one's site-packages (the
    # second command finds them installed by the first all the same), dofsplat does not
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(system_site_packages=True, with_pip=True).create(env_dir)
    bin_dir = env_dir / "bin"
    env = {k: v for k, v in os.environ.items()
           if k not in ("DOFSPLAT_KERNEL_DIR", "PYTHONPATH", "VIRTUAL_ENV")}
    env.update(PATH=f"{bin_dir}{os.pathsep}{env['PATH']}", VIRTUAL_ENV=str(env_dir),
               XDG_CACHE_HOME=str(tmp_path / "cache"), PIP_DISABLE_PIP_VERSION_CHECK="1")
    site = Path(subprocess.check_output(
        [str(bin_dir / "python3"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        text=True).strip())

    # the first command, in a copy of the checkout (pip builds beside the sources)
    source = tmp_path / "dofsplat-src"
    files = subprocess.check_output(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT,
                                    text=True).split("\n")
    for name in filter(None, files):
        if (ROOT / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, source / name)
    run(demo_line, source, env)
    assert (source / "demo.png").stat().st_size > 10_000
    assert (site / "dofsplat" / "splat" / "subaperture.py").is_file()  # a regular copy
    assert kernel_files(site) == [], "numba wrote compiled kernels inside the install"
    assert kernel_files(tmp_path / "cache" / "dofsplat" / "kernels"), \
        "the kernels were not cached in the user's cache folder"

    # the second command's install, in this checkout (so that the demo below loads the
    # kernels this test session compiled for its sources, from its kernel folder, rather
    # than compiling them all again), then the demo from a folder that is no checkout
    run(install_part(test_line), ROOT, env)
    leftovers = sorted(str(p.relative_to(site)) for p in (site / "dofsplat").rglob("*")) \
        if (site / "dofsplat").exists() else []
    assert leftovers == [], f"the regular copy left files behind: {leftovers[:5]}"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env["DOFSPLAT_KERNEL_DIR"] = os.environ.get("DOFSPLAT_KERNEL_DIR", "")
    result = run("dofsplat demo -o demo.png --size 160x120", elsewhere, env)
    assert (elsewhere / "demo.png").stat().st_size > 1_000, result.stderr
    where = subprocess.check_output([str(bin_dir / "python3"), "-c",
                                     "import dofsplat; print(dofsplat.__file__)"],
                                    cwd=elsewhere, env=env, text=True).strip()
    assert Path(where).resolve().is_relative_to(ROOT.resolve())  # the editable install
