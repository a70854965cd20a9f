"""numba kernels are cached on disk (a second process loads them), and an unwritable cache location is no error."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _run(code: str, env_updates: dict[str, str], drop: tuple[str, ...] = (), cwd: Path | None = None) -> dict:
    """Run ``code`` in a fresh interpreter (the numba cache only matters across processes); it prints one JSON line."""
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env.update(env_updates)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(cwd) if cwd else "", str(REPO)) if p)
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True, text=True,
                         timeout=300, cwd=cwd or REPO)
    assert out.returncode == 0, out.stderr
    return {"result": json.loads(out.stdout.strip().splitlines()[-1]), "stderr": out.stderr}


NMS_PROBE = """
    import json
    import numpy as np
    from detector.ops import rotated_nms
    from detector.ops.iou import _nms_kernel
    boxes = np.array([[0, 0, 0, 2, 1, 1, 0.3], [0.1, 0, 0, 2, 1, 1, 0.2], [5, 5, 0, 1, 1, 1, 0]])
    kept = rotated_nms(boxes, np.array([0.9, 0.8, 0.7]), 0.5).tolist()
    st = _nms_kernel.stats
    print(json.dumps({"kept": kept, "hits": sum(st.cache_hits.values()), "misses": sum(st.cache_misses.values())}))
"""


@pytest.mark.slow
def test_second_process_loads_the_compiled_kernels(tmp_path: Path) -> None:
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "cache")}  # numba's first choice: keeps the test off the source tree
    first = _run(NMS_PROBE, env)["result"]
    second = _run(NMS_PROBE, env)["result"]
    assert first["kept"] == second["kept"] == [0, 2]
    assert first["misses"] == 1 and first["hits"] == 0  # compiled, then saved
    assert second["hits"] == 1 and second["misses"] == 0  # loaded, not compiled
    assert any((tmp_path / "cache").rglob("*.nbi"))


MODULE = """
    import numpy as np
    from mpchair.core.jit import njit_cached

    @njit_cached
    def total(a):
        s = 0.0
        for v in a:
            s += v
        return s
"""

USE_MODULE = """
    import json, warnings
    import numpy as np
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import kernels_probe
    print(json.dumps({"total": kernels_probe.total(np.arange(5.0)),
                      "warnings": [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)],
                      "cached": kernels_probe.total._cache is not None
                                and type(kernels_probe.total._cache).__name__ != "NullCache"}))
"""


def test_unwritable_cache_locations_fall_back_to_an_uncached_kernel(tmp_path: Path) -> None:
    src = tmp_path / "pkg"
    src.mkdir()
    (src / "kernels_probe.py").write_text(textwrap.dedent(MODULE))
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("")
    # Nothing can be created under a regular file, even as root: no __pycache__ beside the source, no user cache.
    (src / "__pycache__").write_text("")
    env = {"HOME": str(blocker), "XDG_CACHE_HOME": str(blocker / "cache")}
    got = _run(USE_MODULE, env, drop=("NUMBA_CACHE_DIR",), cwd=src)["result"]
    assert got["total"] == 10.0
    assert not got["cached"]
    assert len(got["warnings"]) == 1 and "NUMBA_CACHE_DIR" in got["warnings"][0]

    # the same module with a writable NUMBA_CACHE_DIR is cached and silent
    got = _run(USE_MODULE, {**env, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}, cwd=src)["result"]
    assert got["total"] == 10.0 and got["cached"] and got["warnings"] == []
