"""A labgrid lab on this machine, for trying ``--place`` and for tests and benchmarks: a real
``labgrid-coordinator`` on 127.0.0.1 and a free port, and a real ``labgrid-exporter``
publishing an exporter config, both ended when the block ends (and with this process,
however it ends)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from hil.core.libc import die_with_parent_signal

BIN = Path(sys.executable).parent


def start(argv: list[str], log: Path, env: dict[str, str] | None = None
          ) -> subprocess.Popen[bytes]:
    """``argv`` started in ``log``'s folder, its output to ``log`` (a pipe nobody reads would
    fill and stop it)."""
    with log.open("wb") as out:
        return subprocess.Popen(argv, cwd=log.parent, env=env, stdout=out,
                                stderr=subprocess.STDOUT, preexec_fn=die_with_parent_signal)


def stop(process: subprocess.Popen[bytes]) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=30)


def _line_of(log: Path, marker: str, process: subprocess.Popen[bytes], timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while True:
        text = log.read_text(errors="replace")
        for line in text.splitlines():
            if marker in line:
                return line
        if process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"{log.name}: no {marker!r}: {text[-2000:]}")
        time.sleep(0.1)


def published(address: str, exporter: str, resources: Iterable[tuple[str, str]]) -> bool:
    """Whether the coordinator lists every ``(group, resource name)`` of ``exporter``,
    available."""
    from labgrid.remote.client import start_session

    session = start_session(address)
    try:
        groups = session.resources.get(exporter, {})
        entries = [groups.get(group, {}).get(name) for group, name in resources]
        return all(entry is not None and entry.avail for entry in entries)
    finally:
        session.loop.run_until_complete(session.stop())
        session.loop.run_until_complete(session.close())


@contextlib.contextmanager
def local_lab(folder: Path, exporter_yaml: str, resources: Iterable[tuple[str, str]], *,
              exporter: str = "hil-lab", timeout_s: float = 90.0,
              env: dict[str, str] | None = None) -> Iterator[str]:
    """The coordinator's address, once the exporter (named ``exporter``, publishing
    ``exporter_yaml``) has published every ``(group, resource name)`` of ``resources``;
    logs and the coordinator's state in ``folder``. Readiness is polled from the coordinator,
    at most ``timeout_s`` seconds."""
    folder.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ if env is None else env)
    env.pop("LG_COORDINATOR", None)
    processes = []
    try:
        coordinator = start([str(BIN / "labgrid-coordinator"), "--listen", "127.0.0.1:0"],
                            folder / "coordinator.log", env)
        processes.append(coordinator)
        line = _line_of(folder / "coordinator.log", "listening on", coordinator, timeout_s)
        address = f"127.0.0.1:{line.rsplit(':', 1)[1].strip()}"
        (folder / "exporter.yaml").write_text(exporter_yaml)
        processes.append(start([str(BIN / "labgrid-exporter"), "-c", address, "-n", exporter,
                                "--hostname", "127.0.0.1", "exporter.yaml"],
                               folder / "exporter.log", env))
        wanted = list(resources)
        deadline = time.monotonic() + timeout_s
        while not published(address, exporter, wanted):
            log = (folder / "exporter.log").read_text(errors="replace")[-2000:]
            if processes[-1].poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the exporter published nothing: {log}")
            time.sleep(0.2)
        yield address
    finally:
        for process in reversed(processes):
            stop(process)
