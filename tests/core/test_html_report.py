"""The HTML report (``hil report F --html F.html``, ``hil.core.html_report``): one file that
holds the session and loads nothing from outside, tried on real lockstep sessions (two servo
runs of 0.5 s, one bench cycle) made by ``hil`` in a folder outside the repository (a process
for the first, the command line in this process for the others), then opened in a real
headless Chromium where one is installed."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from hil.core.html_report import write_comparison_html, write_session_html
from hil.core.html_report.decimate import minmax_decimate
from hil.core.recording.reader import read_session
from hil.core.report import kpis
from hil.errors import UsageError
from tests.cli import hil_here, hil_in

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

SIGNAL = "/drive/command:error_deg"


def record(folder: Path, runs: dict[str, list[str]]) -> Path:
    """``hil RUN --out NAME.mcap`` for each run in ``folder``: the first by a ``hil`` process,
    the others meanwhile by the command line in this process (a process start costs CPU)."""
    (first, argv), *others = runs.items()
    process = subprocess.Popen(
        [sys.executable, "-m", "hil", *argv, "--out", f"{first}.mcap", "--quiet"], cwd=folder,
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    for name, here in others:
        assert hil_in(folder, *here, "--out", f"{name}.mcap", "--quiet") == 0, name
    _, err = process.communicate(timeout=180)
    assert process.returncode == 0, f"{first}: {err}"
    return folder


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """A user's folder with two lockstep servo sessions: a PID run with a limit (the
    baseline), the same with a slower integrator (the candidate)."""
    limit = ["--limit", "rms_error_deg<=0.5"]
    return record(tmp_path_factory.mktemp("html"), {
        "base": ["servo", "run", "--controller", "pid", "--duration", "0.5", *limit],
        "cand": ["servo", "run", "--controller", "pid", "--duration", "0.5",
                 "--param", "ti_us=8000", *limit]})


@pytest.fixture(scope="module")
def bench_folder(tmp_path_factory) -> Path:
    """A user's folder with one bench cycle (28 s of session) of the BC."""
    folder = tmp_path_factory.mktemp("html-bench")
    assert hil_in(folder, "bench", "run", "--controller", "bc", "--cycles", "1", "--out",
                  "bench.mcap", "--quiet") == 0
    return folder


def comparison_of(base: Path, cand: Path) -> dict:
    """A ``hil compare --json`` document of the two sessions: their KPIs within 2 %, and the
    tracking error within 0.001 deg tick for tick, its worst point where it is."""
    b, c = read_session(base), read_session(cand)
    rows = []
    for name in ("rms_error_deg", "max_error_deg"):
        kb, kc = kpis(b)[name], kpis(c)[name]
        rows.append({"kind": "kpi", "name": name, "baseline": kb, "candidate": kc,
                     "difference": kc - kb, "tolerance": "rel 2%",
                     "passed": abs(kc - kb) <= 0.02 * abs(kb), "worst_t_s": None})
    eb, ec = b.arrays("/drive/command"), c.arrays("/drive/command")
    diff = np.abs(ec["error_deg"] - eb["error_deg"])
    worst = int(np.argmax(diff))
    rows.append({"kind": "signal", "name": SIGNAL, "baseline": float(eb["error_deg"][worst]),
                 "candidate": float(ec["error_deg"][worst]),
                 "difference": float(diff[worst] - 0.001), "tolerance": "abs 0.001",
                 "passed": bool(diff[worst] <= 0.001),
                 "worst_t_s": float((eb["log_time_ns"][worst] - b.time_range_ns()[0]) / 1e9)})
    return {"baseline": str(base), "candidate": str(cand), "application": "servo",
            "alignment": "lockstep", "passed": all(r["passed"] for r in rows), "rows": rows,
            "notes": ["lockstep sessions: compared tick for tick"]}


class Page(HTMLParser):
    """What a page would make a browser fetch (script src, link href, img src...), its
    Content-Security-Policy, and its visible text."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.fetches: list[str] = []
        self.csp = ""
        self.words: list[str] = []
        self._in_script = False
        self.feed(text)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        found = dict(attrs)
        self._in_script = tag in ("script", "style")
        for name in ("src", "href", "data", "action", "poster", "srcset"):
            if found.get(name):
                self.fetches.append(f"<{tag} {name}={found[name]}>")
        if tag in ("link", "iframe", "object", "embed", "base"):
            self.fetches.append(f"<{tag}>")
        if tag == "meta" and found.get("http-equiv") == "Content-Security-Policy":
            self.csp = found.get("content") or ""

    def handle_endtag(self, tag: str) -> None:
        self._in_script = False

    def handle_data(self, data: str) -> None:
        if not self._in_script and data.strip():
            self.words.append(data.strip())

    @property
    def text(self) -> str:
        return " ".join(self.words)


def test_minmax_decimation_keeps_every_peak():
    t = np.arange(100_000) / 1000.0
    y = np.sin(t)
    y[12_345], y[67_890], y[99_999] = 5.0, -7.0, np.nan
    td, yd = minmax_decimate(t, y, 1000)
    assert yd.size <= 1000 and np.all(np.diff(td) > 0)
    assert 5.0 in yd and -7.0 in yd and not np.isnan(yd).any()   # a NaN never hides a number
    assert td[np.flatnonzero(yd == 5.0)[0]] == t[12_345]
    short = np.arange(10.0)
    assert minmax_decimate(short, short, 10)[1] is short


def test_report_html_from_the_command_line(folder, capfd):
    done = hil_here(capfd, "report", "base.mcap", "--html", "out/base.html", "--json",
                    cwd=folder)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["html"] == "out/base.html"
    text = (folder / "out" / "base.html").read_text(encoding="utf-8")
    page = Page(text)
    assert page.fetches == []                      # nothing for the browser to fetch
    assert "default-src 'none'" in page.csp         # and the browser would refuse it
    assert text.count("Plotly.newPlot(") == 2      # the signals and the loop histogram
    words = page.text
    for expected in ("hil report: base.mcap", "PASSED (completed)", "rms_error_deg<=0.5",
                     "holds", "session.start", "Loop timing", "SYNC to reply",
                     "/drive/feedback"):
        assert expected in words, expected
    for panel in ("tracking error", "motor current", "current limit 1000 mA",
                  "loop tick time per task"):
        assert panel in text, panel
    assert "Decimated" not in words and "Damage" not in words


def test_long_signals_are_decimated_and_the_page_says_so(folder, tmp_path, capsys):
    stats = write_session_html(str(folder / "base.mcap"), str(tmp_path / "d.html"),
                               max_points=200)
    assert stats.traces == 5 and stats.points <= 5 * 200   # the 5 signals over time
    assert "tracking: position" in stats.decimated          # 1000 ticks > 200 points
    assert stats.bytes == (tmp_path / "d.html").stat().st_size
    assert hil_here(capsys, "report", folder / "base.mcap", "--html", tmp_path / "c.html",
                    "--max-points", "200").returncode == 0
    for page in ("d.html", "c.html"):
        words = Page((tmp_path / page).read_text(encoding="utf-8")).text
        assert f"Decimated for size: {len(stats.decimated)} of 5 traces" in words
        assert "at most 200 points each" in words


def test_bad_html_options_are_one_line(folder, tmp_path, capfd):
    """A variant of the command line run above: ``hil`` in this process."""
    for argv, message in (
            (["--max-points", "300"], "--max-points N (points per trace) needs --html"),
            (["--html", "x.html", "--max-points", "1"], "at least 2 points per trace"),
            (["--html", "x.html", "--events"], "not with --events or --topic")):
        done = hil_here(capfd, "report", "base.mcap", *argv, cwd=folder)
        assert done.returncode == 2 and message in done.stderr, done.stderr
        assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert not (folder / "x.html").exists()
    with pytest.raises(UsageError, match="max_points: expected an integer of at least 2"):
        write_session_html(str(folder / "base.mcap"), str(tmp_path / "x.html"), max_points=0)


def test_comparison_html_overlays_both_sessions_and_marks_the_worst_point(folder, tmp_path):
    comparison = comparison_of(folder / "base.mcap", folder / "cand.mcap")
    assert comparison["passed"] is False          # a slower integrator tracks differently
    out = tmp_path / "cmp" / "cmp.html"
    stats = write_comparison_html(str(folder / "base.mcap"), str(folder / "cand.mcap"),
                                  comparison, str(out), signals=["/drive/feedback:current_mA"])
    text = out.read_text(encoding="utf-8")
    page = Page(text)
    assert page.fetches == [] and stats.plots == 2
    assert stats.traces == 10 + 4   # 5 signals of each session, 2 compared signals of each
    words = page.text
    assert "FAILED" in words and "lockstep" in words
    assert "compared tick for tick" in words
    worst = comparison["rows"][-1]
    assert f"{worst['worst_t_s']:.6g}" in words and "FAIL" in words
    for name in ("position (baseline)", "position (candidate)", SIGNAL,
                 "/drive/feedback:current_mA",
                 f"worst: difference {worst['difference']:.6g} at {worst['worst_t_s']:.6g} s"):
        assert name in text.replace("\\u002f", "/"), name   # plotly writes / as \u002f
    comparison["rows"].append({**worst, "name": "/drive/gone:x_deg"})   # not in the sessions
    write_comparison_html(str(folder / "base.mcap"), str(folder / "cand.mcap"), comparison,
                          str(out))
    assert "Not drawn: signal '/drive/gone:x_deg': no topic '/drive/gone'" in Page(
        out.read_text(encoding="utf-8")).text
    with pytest.raises(UsageError, match=r"no numeric field 'nope'; fields: .*error_deg"):
        write_comparison_html(str(folder / "base.mcap"), str(folder / "cand.mcap"),
                              comparison, str(tmp_path / "x.html"),
                              signals=["/drive/command:nope"])


def test_a_recovered_file_shows_its_damage(folder, tmp_path, capfd):
    """The file cut just after its last chunk (its summary lost, as when the writer is
    killed): every message is read, and the page says what was lost."""
    with open(folder / "base.mcap", "rb") as f:
        end = max(c.chunk_start_offset + c.chunk_length
                  for c in make_reader(f).get_summary().chunk_indexes)
    (tmp_path / "cut.mcap").write_bytes((folder / "base.mcap").read_bytes()[: end + 10])
    done = hil_here(capfd, "report", "cut.mcap", "--html", "cut.html", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    words = Page((tmp_path / "cut.html").read_text(encoding="utf-8")).text
    assert "Damage: a recovered file" in words
    assert "RECOVERED:" in words and "truncated:" in words
    assert "tracking error" in (tmp_path / "cut.html").read_text()   # what was read


def test_bench_report_draws_power_relays_and_levels(bench_folder, capfd):
    done = hil_here(capfd, "report", "bench.mcap", "--html", "bench.html", cwd=bench_folder)
    assert done.returncode == 0, done.stderr
    text = (bench_folder / "bench.html").read_text(encoding="utf-8")
    words = Page(text).text
    for expected in ("total apparent power", "relays (on = raised)", "resource levels",
                     "J1_VA", "bench.open", "contracted", "q1 bound"):
        assert expected in text, expected
    assert "Decimated for size" not in words   # 2800 samples fit; relays: their changes only


# -- in a browser ------------------------------------------------------------------------------

CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync")

PLOTS = """
return Array.from(document.querySelectorAll('.plotly-graph-div')).map(div => ({
  drawn: div.classList.contains('js-plotly-plot') && div.querySelector('.main-svg') !== null,
  given: (div.data || []).length,
  traces: div.querySelectorAll('.scatterlayer .trace').length,
  lines: Array.from(div.querySelectorAll('.scatterlayer path.js-line'))
    .filter(p => (p.getAttribute('d') || '').length > 10).length,
  lineTraces: (div.data || []).filter(t => t.mode === 'lines').length}));
"""


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    """Headless Chromium driven by selenium through Debian's chromedriver, logging the
    console and every request the page makes."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver_path = shutil.which("chromedriver")
    if chromium is None or driver_path is None:
        pytest.skip("no Chromium and chromedriver here (Debian: apt-get install chromium "
                    "chromium-driver): the HTML report is not opened in a browser")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={tmp_path_factory.mktemp('chromium')}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    driver = webdriver.Chrome(service=Service(executable_path=driver_path), options=options)
    driver.set_page_load_timeout(120)
    yield driver
    driver.quit()


def open_page(driver, path: Path) -> tuple[list[dict], list[str], list[str]]:
    """Load ``path`` from file://, wait for plotly to draw; its plots, the console's errors
    and the URLs the page requested (its own document's requests: the browser's own pages,
    such as a new tab's, are not the report's)."""
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get_log("browser"), driver.get_log("performance")     # start from a clean slate
    driver.get(path.as_uri())
    WebDriverWait(driver, 120).until(lambda d: d.execute_script(PLOTS) and all(
        p["drawn"] and p["traces"] == p["given"] for p in d.execute_script(PLOTS)))
    plots = driver.execute_script(PLOTS)
    errors = [entry["message"] for entry in driver.get_log("browser")
              if entry["level"] == "SEVERE"]
    requests = [event["params"]["request"]["url"]
                for event in (json.loads(e["message"])["message"]
                              for e in driver.get_log("performance"))
                if event["method"] == "Network.requestWillBeSent"
                and event["params"].get("documentURL") == path.as_uri()]
    return plots, errors, requests


def test_reports_open_in_a_browser_draw_every_plot_and_fetch_nothing(browser, folder,
                                                                      bench_folder, tmp_path):
    write_session_html(str(folder / "base.mcap"), str(tmp_path / "servo.html"))
    write_session_html(str(bench_folder / "bench.mcap"), str(tmp_path / "bench.html"))
    write_comparison_html(str(folder / "base.mcap"), str(folder / "cand.mcap"),
                          comparison_of(folder / "base.mcap", folder / "cand.mcap"),
                          str(tmp_path / "cmp.html"))
    for path in (tmp_path / "servo.html", tmp_path / "bench.html", tmp_path / "cmp.html"):
        plots, errors, requests = open_page(browser, path)
        assert errors == [], path.name
        assert len(plots) == 2, path.name
        for plot in plots:
            assert plot["given"] > 0 and plot["traces"] == plot["given"], (path.name, plot)
            assert plot["lines"] >= plot["lineTraces"] > 0, (path.name, plot)
        assert set(requests) == {path.as_uri()}, (path.name, requests)
