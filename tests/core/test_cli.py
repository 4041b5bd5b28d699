import json
import subprocess
import sys

import pytest

from hil.cli.main import main
from hil.core.clock import SimClock
from hil.core.loop import FunctionTask
from hil.core.session import Session


@pytest.fixture
def session_file(tmp_path):
    path = tmp_path / "run.mcap"
    session = Session(str(path), SimClock(), 0.01, kind="test", handle_signals=False)
    topic = session.topic("/x", {"type": "object", "title": "X"})
    session.add_task(FunctionTask("sample", 1, write=lambda t: topic.log(t, {"t": t})))
    session.add_task(FunctionTask("control", 100))
    session.run(duration_s=5)
    session.close(kpis={"peak_VA": 600.5})
    return path


def test_help_lists_every_command():
    out = subprocess.run([sys.executable, "-m", "hil", "--help"], capture_output=True,
                         text=True, check=True).stdout
    for command in ("demo", "bench", "servo", "empc", "identify", "emulate", "report"):
        assert command in out


def test_report_json_has_the_contract_keys(session_file, capsys):
    assert main(["report", str(session_file), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["topics"]["/x"] == 500
    assert summary["topics"]["/loop/sample/timing"] == 5
    assert summary["duration_s"] == pytest.approx(4.99, abs=0.011)
    assert summary["recovered"] is False
    assert summary["loop"]["sample"]["runs"] == 500
    assert summary["loop"]["control"]["runs"] == 5
    assert summary["loop"]["sample"]["missed"] == 0
    assert summary["kpis"] == {"peak_VA": 600.5}


def test_report_text_and_png(session_file, tmp_path, capsys):
    png = tmp_path / "r.png"
    assert main(["report", str(session_file), "--out", str(png)]) == 0
    text = capsys.readouterr().out
    assert "/x" in text and "sample" in text and "peak_VA" in text
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["report", "/nonexistent/x.mcap"], "no such session file"),
        (["report", "{bad}"], "not an MCAP session file"),
    ],
)
def test_bad_session_files_give_one_line_errors(argv, message, tmp_path, capsys):
    if argv[1] == "{bad}":
        bad = tmp_path / "bad.mcap"
        bad.write_bytes(b"this is not mcap at all")
        argv = ["report", str(bad)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize(
    "argv",
    [
        ["bench", "run", "--controller", "eec", "--cycles", "0"],
        ["bench", "run", "--controller", "eec", "--limit", "J2_VA=5"],
        ["servo", "run", "--controller", "pid", "--param", "gain"],
        ["emulate", "drive", "--socketcand", "localhost:99999"],
        ["nosuchcommand"],
    ],
)
def test_bad_arguments_exit_2_with_a_usage_line(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err


@pytest.mark.parametrize(("argv", "message"), [
    (["bench", "run", "--controller", "xyz"], "'xyz': no such name (registered: bc, eec"),
    (["servo", "run", "--controller", "eec"], "a servo controller is built as "
                                              "Class(reference, params)"),
    (["servo", "run", "--controller", "mpc", "--param", "hx=3"],
     "unknown key 'hx' (known here: ert, hp, ht, hu, q, r, umax)"),
])
def test_bad_controller_specs_exit_2_with_one_line_and_no_session(argv, message, capsys,
                                                                  tmp_path):
    out = tmp_path / "x.mcap"
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hil: error: ") and "\n" not in err and message in err, err
    assert not out.exists()
