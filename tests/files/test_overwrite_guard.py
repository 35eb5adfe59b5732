"""``--overwrite`` replaces only files pemviz wrote: the report page, its Markdown twin and the JUnit test case are
told from a user's HTML, notes or build XML by their signature (:data:`pemviz.io.files.SIGNATURES`), as recordings,
Parquet tables and result documents are by their leading bytes."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pemviz import cli
from pemviz.io.files import SIGNATURES, written_by_pemviz

SMALL_RUN = ["run", "--preset", "quick", "--k", "1", "--n", "10", "--n-final", "10", "--ce-epochs", "1", "--no-record"]


def cli_line(capsys, *args: str) -> tuple[int, str]:
    try:
        code = cli.main(list(args))
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr().err.strip()


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> Path:
    """A folder with a small run's result document, report page, Markdown twin and JUnit file."""
    tmp = tmp_path_factory.mktemp("written")
    outputs = ["--json", str(tmp / "r.json"), "--report", str(tmp / "r.html"), "--junit", str(tmp / "r.xml")]
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert cli.main([*SMALL_RUN, "--require", "p < 0.5", "--max-sims", "2000", *outputs]) in (0, 1, 3)
    return tmp


@pytest.mark.parametrize("name", ["r.html", "r.md", "r.xml", "r.json"])
def test_what_pemviz_wrote_is_recognised(written, name):
    assert written_by_pemviz(written / name)


@settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(suffix=st.sampled_from(sorted(SIGNATURES)), text=st.text(max_size=300), prefix=st.sampled_from(["", "<html>"]))
def test_a_text_without_the_signature_is_never_taken_for_pemviz_s(tmp_path_factory, suffix, text, prefix):
    body = (prefix + text).encode("utf-8", "surrogatepass")
    if SIGNATURES[suffix] in body:
        return
    path = tmp_path_factory.mktemp("user") / f"mine{suffix}"
    path.write_bytes(body)
    assert not written_by_pemviz(path)


@pytest.mark.parametrize("suffix", [".html", ".md"])
def test_report_overwrite_keeps_a_users_page_and_replaces_its_own(written, tmp_path, capsys, suffix):
    page = tmp_path / "mine.html"
    mine = page.with_suffix(suffix)
    mine.write_text("<!doctype html><title>my notes</title>" if suffix == ".html" else "# my notes\n")
    before = mine.read_text()
    code, err = cli_line(capsys, "report", str(written / "r.json"), "--out", str(page), "--overwrite")
    assert code == 2 and len(err.splitlines()) == 1
    assert err == (
        f"pemviz report: error: --out{' (its Markdown twin)' if suffix == '.md' else ''} {mine}: exists and is not "
        f"a {suffix} file pemviz wrote; not replacing it"
    )
    assert mine.read_text() == before and sorted(p.name for p in tmp_path.iterdir()) == [mine.name]
    code, err = cli_line(capsys, "report", str(written / "r.json"), "--out", str(written / "r.html"), "--overwrite")
    assert code == 0 and err == f"report: {written / 'r.html'} (and {written / 'r.md'})"


def test_run_overwrite_keeps_a_users_report_and_junit_file(tmp_path, capsys):
    (tmp_path / "mine.html").write_text("<html><body>my page</body></html>")
    (tmp_path / "build.xml").write_text('<?xml version="1.0"?><project name="mine"/>')
    code, err = cli_line(capsys, *SMALL_RUN, "--report", str(tmp_path / "mine.html"), "--overwrite")
    assert (code, err) == (
        2,
        f"pemviz run: error: --report {tmp_path / 'mine.html'}: exists and is not a .html file pemviz wrote; "
        "not replacing it",
    )
    req = ["--require", "p < 0.5", "--junit", str(tmp_path / "build.xml"), "--overwrite"]
    code, err = cli_line(capsys, *SMALL_RUN, *req)
    assert (code, err) == (
        2,
        f"pemviz run: error: --junit {tmp_path / 'build.xml'}: exists and is not a .xml file pemviz wrote; "
        "not replacing it",
    )
    assert (tmp_path / "mine.html").read_text() == "<html><body>my page</body></html>"
    assert (tmp_path / "build.xml").read_text() == '<?xml version="1.0"?><project name="mine"/>'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["build.xml", "mine.html"]
