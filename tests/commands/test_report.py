"""The safety-case report: ``pemviz run --report``, ``pemviz report RESULT.json`` and ``pemviz report RUN.rrd`` (the
result document a run writes beside its recording) write the same self-contained page, which opens in headless
Chromium with the network cut and holds the numbers the console printed."""

from __future__ import annotations

import contextlib
import html
import io
import json
import os
import re
import shutil
from pathlib import Path

import pytest
from pemviz.cli import main
from pemviz.sinks.report import document_sha256, report_html, severity_svg

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]

RUNS = {
    "braking": ["run"],
    "cut-in": ["run", "--scenario", "cut-in", "--n", "1000"],  # 260 failures at seed 0, as 777 at 3,000
}


@pytest.fixture(scope="module", params=sorted(RUNS))
def reported(request, tmp_path_factory):
    tmp = tmp_path_factory.mktemp(f"report-{request.param}")
    page, result, recording = tmp / "page.html", tmp / "result.json", tmp / "run.rrd"
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main([*RUNS[request.param], "--save", str(recording), "--json", str(result), "--report", str(page)]) == 0
    return request.param, out.getvalue(), page, result


def _console_numbers(stdout: str) -> list[str]:
    """The lines under the table that carry the estimate and the severity curve."""
    return [
        line.strip()
        for line in stdout.splitlines()
        if line.startswith(
            ("mu_hat = ", "no failure seen in", "severity:", "  gap <", "  clearance <", "  the spec's failure")
        )
    ]


def test_the_report_holds_every_line_the_console_printed(reported):
    scene, stdout, page, result = reported
    lines = _console_numbers(stdout)
    assert len(lines) >= 4, stdout  # the estimate, the curve's title and its points
    text = page.with_suffix(".md").read_text()
    for line in lines:
        assert line in text, line
    doc = json.loads(result.read_text())
    assert doc["problem"]["formula"] and doc["inputs"][0]["what"] == "detection PEM"
    assert re.fullmatch(r"[0-9a-f]{64}", doc["inputs"][0]["sha256"])
    assert document_sha256(doc) in page.read_text()
    if scene == "cut-in":
        assert [i["what"] for i in doc["inputs"]] == ["detection PEM", "noise PEM"]


def test_pemviz_report_from_the_result_writes_the_same_page(reported, tmp_path):
    _, _, page, result = reported
    again = tmp_path / "again.html"
    assert main(["report", str(result), "--out", str(again)]) == 0
    assert again.read_text() == page.read_text()
    assert again.with_suffix(".md").read_text() == page.with_suffix(".md").read_text()


def test_pemviz_report_from_the_recording_writes_the_same_page(reported, tmp_path):
    """A run that saves its recording writes its result document beside it (run.rrd -> run.result.json): the report
    of the recording is the report of the run."""
    _, stdout, page, result = reported
    recording = result.parent / "run.rrd"
    beside = result.parent / "run.result.json"
    assert recording.stat().st_size > 0 and beside.read_text() == result.read_text()
    assert json.loads(beside.read_text())["recording"] == str(recording)
    again = tmp_path / "from-recording.html"
    assert main(["report", str(recording), "--out", str(again)]) == 0
    assert again.read_text() == page.read_text()
    for line in _console_numbers(stdout):
        assert line in again.with_suffix(".md").read_text(), line
    assert main(["report", str(recording), "--out", str(again)]) == 2  # an existing page is kept without --overwrite


def test_a_result_document_in_the_way_of_a_recording_is_refused_before_any_work(tmp_path, capsys):
    (tmp_path / "run.result.json").write_text("{}")
    code = main(["run", "--n", "100", "--save", str(tmp_path / "run.rrd")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "run.result.json" in err and len(err.splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.result.json"]
    assert (tmp_path / "run.result.json").read_text() == "{}"


def test_the_page_opens_offline_in_chromium_and_shows_the_estimate(reported):
    sync_api = pytest.importorskip("playwright.sync_api", reason="the Python playwright package is not installed")
    if not os.path.exists(CHROMIUM):
        pytest.skip("Debian's chromium is not installed (apt-get install chromium)")
    scene, stdout, page, result = reported
    doc = json.loads(result.read_text())
    requests: list[str] = []
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        context = browser.new_context(offline=True)
        tab = context.new_page()
        tab.on("request", lambda r: requests.append(r.url))
        tab.goto(page.as_uri())
        tab.get_by_role("heading", name="Estimate").wait_for()
        body = tab.inner_text("body")
        if doc["severity"]["points"][0]["p"]:
            assert tab.locator("svg[aria-label='severity curve']").count() == (1 if severity_svg(doc) else 0)
        browser.close()
    assert requests == [page.as_uri()]  # nothing but the page itself: no font, script or image from anywhere
    assert f"{scene}" in body and doc["estimate"]["verdict"] in body
    first = _console_numbers(stdout)[0]
    assert first in body


def test_a_report_of_a_bad_source_is_one_line(tmp_path, capsys):
    (tmp_path / "run.rrd").write_bytes(b"RRF2")
    (tmp_path / "other.json").write_text('{"format": "pemviz-rollouts"}')
    (tmp_path / "broken.json").write_text("{")
    cases = [
        (tmp_path / "run.rrd", "a recording without its result document beside it (run.result.json)"),
        (tmp_path / "other.json", "not a pemviz result document"),
        (tmp_path / "broken.json", "not a readable JSON file"),
        (tmp_path / "absent.json", "absent.json: no such file"),
        (tmp_path / "nosuch.rrd", "nosuch.rrd: no such file"),  # the file itself, not its result document
    ]
    for path, message in cases:
        code = main(["report", str(path)])
        err = capsys.readouterr().err.strip()
        assert code == 2 and message in err and len(err.splitlines()) == 1, err
    assert "result document" not in err
    assert not list(tmp_path.glob("*.html"))


@pytest.mark.parametrize("existing", [["r.md"], ["r.html"], ["r.html", "r.md"]])
def test_a_report_onto_an_existing_file_names_both_files_before_any_work(tmp_path, capsys, existing):
    """`pemviz run --report r.html` where r.md (or r.html, or both) exists: one line naming what would be written
    (the page and its twin), what exists and the flag that replaces it; nothing written, no run started. `pemviz
    report` says the same of its --out."""
    for name in existing:
        (tmp_path / name).write_text("kept")
    page, result = tmp_path / "r.html", tmp_path / "result.json"
    fields = {"scenario": "braking", "method": "adaptive", "seed": 0, "estimate": {}, "n_simulations": 1}
    result.write_text(json.dumps({"format": "pemviz-result", **fields}))
    for argv in (
        ["run", "--n", "100", "--no-record", "--report", str(page)],
        ["report", str(result), "--out", str(page)],
    ):
        code = main(argv)
        out = capsys.readouterr()
        err = out.err.strip()
        flag = "--report" if argv[0] == "run" else "--out"
        assert code == 2 and len(err.splitlines()) == 1 and not out.out, err
        assert f"{flag} {page}: writes {page} and its Markdown twin {tmp_path / 'r.md'}; " in err, err
        named = "both exist" if len(existing) == 2 else f"{tmp_path / existing[0]} exists"
        assert f"{named}: give --overwrite to replace" in err, err
        assert all((tmp_path / name).read_text() == "kept" for name in existing)
        assert sorted(p.name for p in tmp_path.iterdir() if p.suffix != ".json") == sorted(existing)


def test_report_html_needs_the_result_fields():
    with pytest.raises(KeyError):
        report_html({"format": "pemviz-result"})


def test_the_report_groups_the_failures_and_their_shares_add_up_to_one(reported):
    """The result document's failures: groups whose shares add up to 1 and counts that add up to the estimate's
    failures, the largest failure first; the page lists the groups."""
    import math

    scene, _, page, result = reported
    doc = json.loads(result.read_text())
    f = doc["failures"]
    assert f["n"] == doc["estimate"]["n_failures"] == sum(g["count"] for g in f["groups"])
    if f["n"] == 0:
        return
    assert math.isclose(sum(g["share"] for g in f["groups"]), 1.0, rel_tol=1e-12)
    shares = [x["share"] for x in f["largest"]]
    assert shares == sorted(shares, reverse=True)
    text = page.with_suffix(".md").read_text()
    assert "## Failures by share of p" in text and f["groups"][0]["label"] in text
    if scene == "braking":
        assert f["basis"].startswith("the last step at which one detection") and len(f["groups"]) >= 2


def test_the_report_shows_the_failures_severity_by_share_as_the_console_printed_it(reported):
    """p(severity | failure) in the result document: bins whose shares add up to 1 and whose counts add up to the
    failures, each of the largest failures with its min distance and impact speed; the page's table and the
    console's line."""
    import math

    scene, stdout, page, result = reported
    doc = json.loads(result.read_text())
    f = doc["failures"]
    if f["n"] == 0:
        return
    sev = f["severity"]
    assert sev["label"] == {"braking": "gap", "cut-in": "clearance"}[scene]
    assert sev["contact"] == {"braking": 0.7, "cut-in": 0.0}[scene]
    assert sev["n"] == sev["n_kept"] == f["n"] == sum(b["count"] for b in sev["bins"]) and sev["covered"] == 1.0
    assert math.isclose(sum(b["share"] for b in sev["bins"]), 1.0, rel_tol=1e-12)
    assert [b["label"] for b in sev["bins"]] == ["no contact", "0-2 m/s", "2-5 m/s", "> 5 m/s"]
    for x in f["largest"]:
        assert x["min_distance"] is not None and (x["impact_speed"] is None or x["impact_speed"] > 0)
    assert sev["text"] in stdout.splitlines() and sev["text"] in doc["console"]
    text = page.with_suffix(".md").read_text()
    assert "## Severity of the failures" in text and "| impact speed | failures | share of p |" in text
    assert f"median min {sev['label']}: {sev['median_min_distance']:.2f} m" in text


@pytest.fixture(scope="module")
def default_run(tmp_path_factory) -> tuple[str, Path, Path]:
    """``pemviz run --no-record --json r.json --report r.html``: (its stdout, the page, the result document)."""
    tmp = tmp_path_factory.mktemp("default")
    page, result = tmp / "r.html", tmp / "r.json"
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main(["run", "--no-record", "--json", str(result), "--report", str(page)]) == 0
    return out.getvalue(), page, result


@pytest.mark.parametrize("uncertainty", [True, False], ids=["pem-uncertainty", "no-spread"])
def test_the_report_says_what_its_number_rests_on(tmp_path, uncertainty, request):
    """`pemviz run [--pem-uncertainty] --report r.html`: a section with the PEM's sha256, the members' median and
    90 % range as the console printed them (or that the spread was not computed, and how), the verdict's checks and
    the limits; checked in headless Chromium. The headline puts the verdict and the spread side by side."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="the Python playwright package is not installed")
    if not os.path.exists(CHROMIUM):
        pytest.skip("Debian's chromium is not installed (apt-get install chromium)")
    if uncertainty:
        page, result = tmp_path / "r.html", tmp_path / "r.json"
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
            assert main(["run", "--no-record", "--pem-uncertainty", "--json", str(result), "--report", str(page)]) == 0
        stdout = out.getvalue()
    else:  # the default run, which the report's words are also checked on (`meant`)
        stdout, page, result = request.getfixturevalue("default_run")
    doc = json.loads(result.read_text())
    jsonschema = pytest.importorskip("jsonschema")
    from conftest import result_schema as schema

    jsonschema.validate(doc, schema())  # the docs' schema, pem_spread included
    sha = next(i["sha256"] for i in doc["inputs"] if i["what"] == "detection PEM")
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        tab = browser.new_context(offline=True).new_page()
        tab.goto(page.as_uri())
        tab.get_by_role("heading", name="What this number rests on").wait_for()
        body = tab.inner_text("body")
        headline = tab.inner_text(".headline")
        if uncertainty:
            tab.screenshot(path=str(tmp_path / "rests_on.png"), full_page=True)
        browser.close()
    assert sha in body and "false positives are not modelled" in body and "check: Pareto k-hat" in body
    if uncertainty:
        # the console's own line: "members: median 2.856e-15, 90 % of them in [3.549e-19, 6.182e-12] (x...)"
        line = next(ln for ln in stdout.splitlines() if "members: median" in ln)
        median, lo, hi = re.search(r"median (\S+), 90 % of them in \[(\S+), (\S+)\]", line).groups()
        members = doc["pem_spread"]["members"]
        assert float(median) == pytest.approx(members["median"]["p"], rel=2e-3)
        assert float(lo) == pytest.approx(members["range90"][0]["p"], rel=2e-3)
        assert float(hi) == pytest.approx(members["range90"][1]["p"], rel=2e-3)
        assert "ensemble members: median" in body and "under the PEM's uncertainty" in headline
        assert doc["estimate"]["verdict"] in headline
    else:
        assert doc["pem_spread"] is None and "not computed for this run" in body and "--pem-uncertainty" in body
        assert "under the PEM's uncertainty" not in headline


MEANINGS = {"reliable": ["run"], "bound-only": ["run", "--preset", "paper"]}
"""A default run (its verdict reliable) and a run whose weights back no interval (the paper's preset: a lower bound
alone), for the report's words against the console's."""


@pytest.fixture(scope="module", params=sorted(MEANINGS))
def meant(request, tmp_path_factory):
    if request.param == "reliable":  # the default run
        stdout, page, result = request.getfixturevalue("default_run")
        doc = json.loads(result.read_text())
        assert doc["estimate"]["verdict"] == "reliable", doc["estimate"]
        return request.param, stdout, page, doc
    tmp = tmp_path_factory.mktemp(f"meaning-{request.param}")
    page, result = tmp / "page.html", tmp / "result.json"
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main([*MEANINGS[request.param], "--no-record", "--json", str(result), "--report", str(page)]) == 0
    doc = json.loads(result.read_text())
    assert (doc["estimate"]["verdict"] == "reliable") == (request.param == "reliable"), doc["estimate"]
    return request.param, out.getvalue(), page, doc


def _md_rows(text: str, section: str) -> list[list[str]]:
    """The cells of each body row of the Markdown table under ``## section``."""
    block = text.split(f"## {section}\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in block.splitlines() if line.startswith("| ")][1:]  # the header off
    return [[c.strip() for c in re.split(r"(?<!\\)\|", row)[1:-1]] for row in rows]


def test_no_check_row_reads_as_failed_when_it_passed(meant):
    """Each check row says what the run found and "passed" exactly when the figure meets the verdict's rule (checked
    here from the document's figures and the rule's own numbers: 10 failures, ESS 20, k-hat min(1 - 1 / log10 N,
    0.7)); a passed row carries no word of failure."""
    import math

    _, _, page, doc = meant
    e = doc["estimate"]
    rows = dict(_md_rows(page.with_suffix(".md").read_text(), "What this number rests on"))
    truth = {
        "check: failures": e["n_failures"] >= 10,
        "check: effective sample size": e["ess"] is not None and e["ess"] >= 20,
        "check: Pareto k-hat": e["k_hat"] is not None and e["k_hat"] <= min(1 - 1 / math.log10(e["n"]), 0.7),
    }
    assert e["sampling"] == "importance"
    for name, passed in truth.items():
        text = rows[name]
        assert text.endswith(", passed") == passed and ("failed" in text) == (not passed), text
        if passed:
            assert not re.search(r"fewer than|below|above|doubtful|unreliable|dominate", text), text
    assert rows["check: failures"].startswith(f"{e['n_failures']:,} failure")
    assert rows["verdict"] == f"{e['verdict']}: {e['reason']}"
    # a verdict short of reliable has a check row that failed: the bound-only run's three pass, its verdict is the
    # failures' own probability (unreliable), which the page names as the check that failed
    failed = [v for k, v in rows.items() if k.startswith("check: ") and "failed" in v]
    assert bool(failed) == (e["verdict"] != "reliable"), rows
    if e["verdict"] != "reliable" and all(truth.values()):
        assert rows["check: the verdict's other checks"] == f"failed ({e['verdict']}): {e['reason']}"


def test_the_report_s_severity_rows_are_the_console_s(meant):
    """The report's severity table says what the console's severity lines say, figure for figure and word for word;
    a level the run does not estimate shows no estimate (the point the weights do not back), and the chart's legend
    names each kind of mark it draws."""
    scene, stdout, page, doc = meant
    lines = stdout.splitlines()
    start = lines.index(doc["severity"]["title"])
    console = [line for line in lines[start + 1 : start + 1 + len(doc["severity"]["points"])]]
    rows = _md_rows(page.with_suffix(".md").read_text(), "Severity")
    assert len(rows) == len(console) == len(doc["severity"]["points"]) >= 5
    for (level, says), line, pt in zip(rows, console, doc["severity"]["points"], strict=True):
        assert re.fullmatch(rf"  {re.escape(level)} +{re.escape(says)}", line), (level, says, line)
        numbers = re.findall(r"\d\.\d+e[-+]\d+", line)
        assert numbers == re.findall(r"\d\.\d+e[-+]\d+", says)
        if pt["shown"] in ("bound", "not reached") and pt["p"]:
            assert f"{pt['p']:.3e}" not in says and says.split(" ")[0] in ("reached", "not"), says
    html_page = page.read_text()
    for _level, says in rows:
        assert f"<td>{html.escape(says)}</td>" in html_page, says
    shown = {pt["shown"] for pt in doc["severity"]["points"][1:]}
    assert ("not reached by any rollout" in html_page) == ("not reached" in shown)
    assert ("95 % lower bound alone" in html_page) == ("bound" in shown or scene == "bound-only")
    if scene == "bound-only":
        assert "not reached" in shown and rows[0][1].split(" ")[1] == ">="  # the failure: its estimate and bound
    else:
        assert "estimate and its 95 % interval: reliable" in html_page


def test_a_scene_with_its_own_detector_reads_no_pem_file(tmp_path):
    """The toy's detector is its own closed form: the report names no PEM file as read (it listed the shipped detection
    and noise PEMs for every scene but braking)."""
    result, page = tmp_path / "toy.json", tmp_path / "toy.html"
    args = ["run", "--scenario", "toy", "--method", "mc", "--n", "200", "--no-record", "--json", str(result)]
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main([*args, "--report", str(page)]) == 0
    doc = json.loads(result.read_text())
    assert doc["inputs"] == []
    text = page.with_suffix(".md").read_text()
    assert "the scenario's own detector (no PEM file read)" in text
    assert "pem_ml-nn.pt" not in text and "noise_hetero-t.pt" not in text
