"""What a lockstep session recorded, reduced to what must not change when the code is
restructured: per topic, the message count and a sha256 over every message's log time and
deterministic fields (exact float reprs); and the KPIs without their wall-clock keys.

Left out, because they measure the computer and not the experiment:

* the ``/loop/<task>/timing`` topics (lateness and phase times);
* ``compute_us`` (``/drive/command``: the controller's step time), ``rtt_us``
  (``/drive/feedback``), ``solve_ms`` (``/eec/plan``: the solver's time);
* the KPIs ``wall_s``, ``realtime_factor``, ``step_us``, ``solve_ms`` and ``mcap`` (a path);
* metadata (versions, start time, command line);
* the port of an emulator on loopback, which the system picks (``127.0.0.1:PORT``).

``python tests/session_digest.py record OUT.json [NAME ...]`` runs the reference experiments
(or the named ones) through ``hil.api`` and writes their digests: the code of any checkout can be
recorded this way and compared with another's (``tests/core/test_same_sessions.py`` compares with
``tests/data/session_digests.json``).

The floats depend on the kernel OpenBLAS picks for the CPU: its AVX-512 kernel (``SkylakeX``)
sums a small matrix product in another order than its AVX2 kernel (``Haswell``), and the last
bits differ. The reference was recorded with ``REFERENCE_BLAS_KERNEL``; ``OPENBLAS_CORETYPE``
set before numpy loads picks that kernel on a CPU that has another.
"""

from __future__ import annotations

import hashlib
import json
import re
import sys
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

LOOPBACK_PORT = re.compile(r"127\.0\.0\.1:\d+")
WALL_CLOCK_FIELDS = {"compute_us", "rtt_us", "solve_ms"}
WALL_CLOCK_KPIS = {"wall_s", "realtime_factor", "step_us", "solve_ms", "mcap"}
#: OpenBLAS's kernel when tests/data/session_digests.json was recorded (threadpoolctl's name)
REFERENCE_BLAS_KERNEL = "Haswell"

#: name -> (function of hil.api, its arguments): short lockstep runs of both applications
EXPERIMENTS: dict[str, tuple[str, dict[str, Any]]] = {
    "bench-eec": ("run_bench", {"controller": "eec", "cycles": 1, "seed": 7}),
    "bench-bc": ("run_bench", {"controller": "bc", "cycles": 1, "seed": 7,
                               "limits": ["total_va<=5000"]}),
    "servo-mpc": ("run_servo", {"controller": "mpc", "reference":
                                "sine:amplitude=2,frequency=10", "duration_s": 0.5}),
    "servo-pid": ("run_servo", {"controller": "pid", "reference":
                                "sine:amplitude=2,frequency=1", "duration_s": 0.5,
                                "limits": ["abs_error_deg<=30"]}),
    "servo-disturbance": ("run_servo", {"controller": "mpc", "reference":
                                        "disturbance:torque=300,start=0.1,end=0.2",
                                        "duration_s": 0.3}),
}


def _clean(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {k: _clean(v) for k, v in sorted(value.items()) if k not in WALL_CLOCK_FIELDS}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if hasattr(value, "tolist"):  # numpy arrays and scalars
        return _clean(value.tolist())
    if isinstance(value, float):
        return repr(value)  # exact
    if isinstance(value, str):
        return LOOPBACK_PORT.sub("127.0.0.1:PORT", value)
    return value


def session_digest(path: str) -> dict[str, dict[str, Any]]:
    """``{topic: {"count": n, "sha256": hex}}`` of every topic but the loop timing."""
    from hil.core.recording.reader import read_session

    data = read_session(path)
    out = {}
    for topic in sorted(data.messages):
        if topic.startswith("/loop/"):
            continue
        digest = hashlib.sha256()
        count = 0
        for t_ns, message in data.topic(topic):
            digest.update(json.dumps([t_ns, _clean(message)], sort_keys=True).encode())
            count += 1
        out[topic] = {"count": count, "sha256": digest.hexdigest()}
    return out


def kpi_digest(kpis: Mapping[str, Any]) -> dict[str, Any]:
    """The KPIs without their wall-clock keys, floats as exact reprs."""
    cleaned: dict[str, Any] = _clean({k: v for k, v in kpis.items()
                                      if k not in WALL_CLOCK_KPIS})
    return cleaned


def record(folder: str, names: list[str] | None = None) -> dict[str, Any]:
    """Run the reference experiments (lockstep) into ``folder``; their digests by name."""
    from hil import api

    results = {}
    for name in names or list(EXPERIMENTS):
        function, arguments = EXPERIMENTS[name]
        run: Callable[..., dict[str, Any]] = getattr(api, function)
        out = str(Path(folder) / f"{name}.mcap")
        kpis = run(**arguments, out=out)
        results[name] = {"kpis": kpi_digest(kpis), "topics": session_digest(out)}
    return results


def blas_kernel() -> str | None:
    """The kernel OpenBLAS picked for this CPU (``Haswell``, ``SkylakeX``...), None without it."""
    import numpy  # noqa: F401  (loads OpenBLAS)
    from threadpoolctl import threadpool_info

    kernels = [lib.get("architecture") for lib in threadpool_info()
               if lib.get("internal_api") == "openblas"]
    return kernels[0] if kernels else None


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] != "record":
        sys.exit("usage: python tests/session_digest.py record OUT.json [NAME ...]")
    with tempfile.TemporaryDirectory() as tmp:
        digests = record(tmp, sys.argv[3:] or None)
        Path(sys.argv[2]).write_text(json.dumps(digests, indent=1, sort_keys=True) + "\n")
