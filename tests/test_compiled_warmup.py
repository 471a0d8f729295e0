"""The kernels' warm-up (:func:`opnav.compiled.warm_up`): what it lists are kernels with those argument
counts, it compiles what numba's cache lacks and a second process finds it cached, quietly; and (slow)
the demo after its warm-up compiles nothing, so no progress bar holds compile time."""

from __future__ import annotations

import inspect
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from opnav import compiled

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


def _run(code: str, cache_dir, timeout: float = 600, prelude: str = "") -> dict:
    """Run ``prelude`` and ``code`` in a fresh interpreter whose numba cache is ``cache_dir``; the one
    line it prints, as JSON."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    env.pop("NUMBA_DISABLE_JIT", None)
    source = textwrap.dedent(prelude) + textwrap.dedent(code)
    result = subprocess.run([sys.executable, "-c", source], capture_output=True, text=True, env=env, timeout=timeout)
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1, f"printed more than its result:\n{result.stdout}"
    return json.loads(lines[0])


def test_every_listed_call_is_a_kernel_with_that_many_arguments():
    assert len(set(compiled.KERNEL_CALLS)) == len(compiled.KERNEL_CALLS)
    for call in compiled.KERNEL_CALLS:
        dispatcher = call.dispatcher()
        assert hasattr(dispatcher, "compile") and type(dispatcher._cache).__name__ == "FunctionCache", call.name
        parameters = inspect.signature(dispatcher.py_func).parameters
        assert len(call.argument_types()) == len(parameters), call.name
        assert call.uses and set(call.uses) <= set(compiled.USES) and call.seconds > 0, call.name


def test_uses_of_a_run():
    assert compiled.uses_of(["ekf"]) == {"ekf"}
    assert compiled.uses_of(["ekf"], images=True) == {"ekf", "images"}
    assert compiled.uses_of(["ekf", "ukf"], compiled_steps=False) == {"filters", "sigma-points"}
    assert compiled.uses_of(["sr-ukf", "pf"]) == {"filters", "sigma-points", "particles"}
    assert {call.function for call in compiled.kernel_calls({"images"})} >= {"_gauss_kernel", "_lit_rays_kernel"}
    assert [call.function for call in compiled.kernel_calls({"ekf"})] == ["ekf_radec_step"]
    with pytest.raises(ValueError, match="unknown kernel uses"):
        compiled.kernel_calls({"frames"})


def test_the_uses_of_run_files():
    from opnav.commands.compile import run_uses
    from opnav.studies.settings import load_run_file

    demo = load_run_file(Path(compiled.__file__).parent / "data" / "demo_run.toml")
    assert run_uses(demo) == {"images", "ekf"}
    s1 = SAMPLES / "s1_jul_both_0.1.toml"
    assert run_uses(load_run_file(s1), ["ekf", "ukf"]) == {"ekf", "ukf"}
    assert run_uses(load_run_file(s1, {"ephemeris_error": "bias"}), ["ekf"]) == {"filters"}
    assert run_uses(load_run_file(SAMPLES / "s3_geo.toml"), None, "images") == {"images", "filters", "sigma-points"}
    # RA/Dec only: compiled steps; the sample's own mode renders frames
    assert run_uses(load_run_file(SAMPLES / "cislunar.toml"), None, "measurements") == {"ekf", "ukf"}
    assert run_uses(load_run_file(SAMPLES / "cislunar.toml")) == {"images", "ekf", "ukf"}
    assert run_uses(load_run_file(SAMPLES / "s4_approach.toml")) == {"filters", "sigma-points"}


def test_the_estimate_schedules_the_longest_first_on_processes_that_pay(monkeypatch):
    big = [call for call in compiled.KERNEL_CALLS if call.function in ("_gauss_kernel", "_integrate_serial")
           and "f8[::1, :]" not in call.signature]
    small = [call for call in compiled.KERNEL_CALLS if call.function in ("_bloom_kernel", "_merge_kernel")]
    assert len(big) == 2 and len(small) == 2
    one = compiled.estimate_s(big + small, 1)
    assert one == pytest.approx(sum(call.seconds for call in big + small))
    assert compiled.estimate_s(big + small, 2) < one
    # a second process that would not pay for its start is not started
    assert compiled.estimate_s(small, 2) == compiled.estimate_s(small, 1)
    assert compiled.estimate_s([], 2) == 0.0
    assert compiled.rounded_s(0.3) == 5 and compiled.rounded_s(21) == 25
    # on a busy machine, longer: 2 cores, 4 other processes running and 2 compiling, each at a third of a core
    monkeypatch.setattr(compiled, "cores", lambda: 2)
    monkeypatch.setattr(compiled.os, "getloadavg", lambda: (5.0, 5.0, 5.0))
    assert compiled.slowdown(2) == 3.0
    assert compiled.estimate_s(big, 2, busy=True) == pytest.approx(3.0 * compiled.estimate_s(big, 2))
    monkeypatch.setattr(compiled.os, "getloadavg", lambda: (0.5, 0.5, 0.5))
    assert compiled.slowdown(2) == 1.0


#: Three cheap kernels in two modules (two cache index files, so two processes compile them).
_CHEAP = ("_interpolate", "_subpixel_kernel", "_cholupdate")
_SELECT = f"""
    from opnav import compiled
    compiled.KERNEL_CALLS = tuple(c for c in compiled.KERNEL_CALLS if c.function in {_CHEAP!r})
    compiled._PROCESS_START_S = 0.0  # so that two processes pay for kernels this cheap
"""


def test_warm_up_compiles_what_is_not_cached_and_the_next_process_finds_it(tmp_path):
    first = _run("""
        import json
        before = [c.function for c in compiled.pending()]
        seen = []
        result = compiled.warm_up(workers=2, progress=lambda call, seconds, error: seen.append(call.function))
        again = compiled.warm_up()
        print(json.dumps({"before": before, "compiled": [c.function for c, _ in result.compiled],
                          "failed": [f"{c.name}: {e}" for c, e in result.failed], "seen": seen,
                          "workers": result.workers, "after": [c.function for c in compiled.pending()],
                          "again_compiled": len(again.compiled), "again_cached": len(again.cached)}))
    """, tmp_path, prelude=_SELECT)
    assert sorted(first["before"]) == sorted(_CHEAP)
    assert first["failed"] == []
    assert sorted(first["compiled"]) == sorted(_CHEAP) == sorted(first["seen"])
    assert first["workers"] == 2
    assert first["after"] == [] and first["again_compiled"] == 0 and first["again_cached"] == len(_CHEAP)
    # a new process: nothing pending, and the first call loads the machine code instead of compiling it
    second = _run("""
        import json
        import numpy as np
        from opnav.filters.sr_ukf import _cholupdate
        pending = [c.function for c in compiled.pending()]
        _cholupdate(np.asfortranarray(np.eye(3)), np.ones(3), 1.0)
        print(json.dumps({"pending": pending, "hits": sum(_cholupdate.stats.cache_hits.values()),
                          "misses": sum(_cholupdate.stats.cache_misses.values())}))
    """, tmp_path, prelude=_SELECT)
    assert second == {"pending": [], "hits": 1, "misses": 0}


def test_the_compile_command_refuses_unknown_uses(capsys):
    from opnav.cli import main

    assert main(["compile", "--uses", "frames"]) == 2
    assert "unknown frames" in capsys.readouterr().err


@pytest.mark.slow
def test_the_demo_compiles_nothing_after_its_warm_up(tmp_path):
    """A fresh numba cache: ``opnav demo``'s warm-up, then its first frames and records compile nothing
    (a kernel the run calls with types :data:`opnav.compiled.KERNEL_CALLS` does not list would)."""
    out = tmp_path / "demo"
    found = _run(f"""
        import contextlib, io, json
        from numba.core import event
        from opnav.cli import main
        import opnav.commands.compile as command

        late, warm = [], {{"done": False}}
        original = command.compile_for_run

        def compile_for_run(*args, **kwargs):
            original(*args, **kwargs)
            warm["done"] = True

        command.compile_for_run = compile_for_run

        class Compiles(event.Listener):
            depth = 0

            def on_start(self, ev):
                self.depth += 1

            def on_end(self, ev):
                self.depth -= 1
                if self.depth == 0 and warm["done"]:
                    function = ev.data["dispatcher"].py_func
                    late.append(f"{{function.__module__}}.{{function.__qualname__}}"
                                f"({{', '.join(str(a) for a in ev.data['args'])}})")

        event.register("numba:compile", Compiles())
        if __name__ == "__main__":
            with contextlib.redirect_stdout(io.StringIO()):
                status = main(["demo", "--out", {str(out)!r}, "--frames", "4", "--no-progress"])
            print(json.dumps({{"status": status, "warmed": warm["done"], "late": late}}))
    """, tmp_path / "numba", timeout=1800)
    assert found["status"] == 0 and found["warmed"]
    assert found["late"] == [], "kernels compiled after the warm-up (add them to opnav.compiled.KERNEL_CALLS)"


def test_a_damaged_kernel_cache_is_compiled_again_not_fatal(tmp_path):
    """A cache file cut short (a full disk, a killed process) is read as a missing one: the kernel
    compiles again, says so in one line, and the next run is quiet."""
    import subprocess
    import sys

    (tmp_path / "twice.py").write_text("from opnav.compiled import kernel\n\n\n@kernel\ndef twice(x):\n"
                                       "    return 2.0 * x\n\n\nprint(twice(3.0))\n")

    def run():
        return subprocess.run([sys.executable, "twice.py"], cwd=tmp_path, capture_output=True, text=True)

    assert run().stdout.strip() == "6.0"
    cache = sorted((tmp_path / "__pycache__").glob("twice.*.nb*"))
    assert {path.suffix for path in cache} == {".nbi", ".nbc"}
    for path in cache:
        path.write_bytes(path.read_bytes()[:7])
    damaged = run()
    assert damaged.returncode == 0 and damaged.stdout.strip() == "6.0", damaged.stderr
    assert "is damaged" in damaged.stderr and "compiling again" in damaged.stderr
    again = run()
    assert again.stdout.strip() == "6.0" and "damaged" not in again.stderr
