"""The wheel works outside the checkout: build it, install it into a new environment, run the demo and a solve.

The new environment reuses the dependencies of the one running the tests (a ``.pth`` file names
its site-packages) but holds its own copy of opnav, installed from the wheel without
dependencies; every command runs from an empty folder, so the checkout is not importable and
everything opnav needs at run time (the star catalog, the demo's run files) must come from the
installed package. The pattern index of the solve is cached where a user's would be
(``$OPNAV_CACHE``, default ``~/.cache/opnav``): the first run builds it (30-60 s).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.slow


def _run(args, *, cwd: Path, env: dict | None = None, timeout_s: float = 600.0) -> subprocess.CompletedProcess:
    result = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True,
                            timeout=timeout_s)
    assert result.returncode == 0, (
        f"{' '.join(str(a) for a in args)} exited {result.returncode}\n"
        f"stdout: {result.stdout[-3000:]}\nstderr: {result.stderr[-3000:]}"
    )
    return result


def _package_files(package_dir: Path) -> set[str]:
    """Files of the installed package outside ``__pycache__`` (where Python and numba cache compiled code)."""
    return {str(p.relative_to(package_dir)) for p in package_dir.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts}


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict:
    work = tmp_path_factory.mktemp("wheel")
    # Build from a copy of the sources: an in-tree build would leave build/ (stale files included
    # in later wheels) and rewrite opnav.egg-info in the checkout.
    source = work / "source"
    shutil.copytree(ROOT / "opnav", source / "opnav",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    dist = work / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", source, "-w", dist], cwd=work)
    (wheel,) = dist.glob("opnav-*.whl")

    env_dir = work / "env"
    _run([sys.executable, "-m", "venv", "--without-pip", env_dir], cwd=work)
    python = env_dir / "bin" / "python"
    purelib = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                        cwd=work).stdout.strip())
    # Install before the dependencies become visible: pip then sees no other opnav to replace.
    _run([sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "--quiet", wheel],
         cwd=work)
    ours = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (purelib / "_opnav_test_dependencies.pth").write_text("".join(f"{p}\n" for p in sorted(ours)))

    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "OPNAV_CATALOG")}
    env["PATH"] = f"{env_dir / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(env_dir)
    run_dir = work / "run"
    run_dir.mkdir()
    return {"env_dir": env_dir, "python": python, "purelib": purelib, "env": env, "run_dir": run_dir,
            "bin": env_dir / "bin"}


def test_wheel_runs_the_demo_and_solves_outside_the_checkout(installed):
    env, run_dir, purelib = installed["env"], installed["run_dir"], installed["purelib"]
    where = json.loads(_run([installed["python"], "-c",
                             "import json, opnav, opnav.catalog as c; "
                             "print(json.dumps([opnav.__file__, str(c.default_catalog_path()), opnav.__version__]))"],
                            cwd=run_dir, env=env).stdout)
    package_dir = purelib / "opnav"
    assert Path(where[0]).resolve().is_relative_to(package_dir.resolve())
    assert Path(where[1]).resolve() == (package_dir / "data" / "stars.npz").resolve()
    assert (package_dir / "data" / "stars.README.md").is_file()
    # the shipped small-body shape (the asteroid-approach sample's) and its note travel with the package
    faces = _run([installed["python"], "-c", "from opnav.shape import read_obj, shipped_shape; "
                  "print(read_obj(shipped_shape()).n_faces)"], cwd=run_dir, env=env).stdout
    assert int(faces) == 5120 and (package_dir / "data" / "asteroid.README.md").is_file()
    before = _package_files(package_dir)

    demo = _run([installed["bin"] / "opnav", "demo", "--out", "demo", "--no-progress"], cwd=run_dir, env=env,
                timeout_s=900.0)
    frame = run_dir / "demo" / "frames" / "frame_00000.fits"
    assert frame.is_file()
    assert json.loads((run_dir / "demo" / "summary.json").read_text())

    solve = _run([installed["bin"] / "opnav", "solve", "demo/frames/frame_00000.fits", "--fov", "1", "--json"],
                 cwd=run_dir, env=env, timeout_s=900.0)
    solution = json.loads(solve.stdout)
    assert solution["matched"] >= 5
    from astropy.io import fits

    header = fits.getheader(frame)
    boresight = np.radians([header["CRVAL1"], header["CRVAL2"]])
    solved = np.radians([solution["ra_deg"], solution["dec_deg"]])
    cos_angle = (np.sin(boresight[1]) * np.sin(solved[1])
                 + np.cos(boresight[1]) * np.cos(solved[1]) * np.cos(boresight[0] - solved[0]))
    assert np.degrees(np.arccos(min(1.0, cos_angle))) < 0.05  # the frame's own pointing, in a 1-degree field

    # Nothing was written into the installed package (caches live elsewhere), and the checkout was not used.
    assert _package_files(package_dir) == before
    assert not list(run_dir.glob("catalogs")) and not (run_dir / "opnav").exists()
