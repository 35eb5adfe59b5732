"""Every screenshot of the README and the user guide is made by a command of one table (``SCREENSHOTS`` in
``benchmarks/screenshots.py``, run by ``python benchmarks/docs_assets.py --screenshots``) and listed in
``assets/screenshots/MANIFEST.md`` with that command; the generation itself is checked, not the pixels: the cheapest
panel and recording screenshots of the table are made into a temporary folder, small (two small runs)."""

from __future__ import annotations

import re
import shutil

import pytest

from conftest import REPO, load_script

shots = load_script(REPO / "benchmarks" / "screenshots.py")
CHEAPEST = {
    "viser_panel.png": ("--width", "800", "--height", "500", "--k", "2", "--set", "N=40", "--set", "N_e=60"),
    "rerun_recording.png": ("--width", "800", "--height", "500", "--min-wait", "3", "--max-wait", "3", "--rrd"),
}
"""The cheapest panel and recording screenshot of the table (one command each: a quick run; the recording's own tab,
no blueprint), and what the check adds to its command: a small window, no wait for the viewer to settle (its
first screenshot, at 3 s or when the wasm viewer first draws: the recording's layout; waiting for two equal
screenshots cost 15-40 s more), a run of two small stages typed
into the panel's form; the recording screenshot shows a small run's recording (``--rrd``, :data:`SMALL_RUN`, followed
by its path) instead of recording ``pemviz run``'s defaults first."""
SMALL_RUN = ("run", "--preset", "quick", "--k", "2", "--n", "30", "--n-final", "40", "--ce-epochs", "5", "--seed", "3")
"""A recording of a second (``pemviz run`` ARGS ``--save PATH``, in-process): what the screenshot shows is the
viewer drawing a pemviz recording, whatever its size."""
REFERENCE = re.compile(r"(?:assets/)?screenshots/([\w.-]+\.png)")


def test_every_image_is_in_the_table_and_the_manifest_and_every_entry_exists() -> None:
    table = shots.by_image()
    on_disk = {p.name for p in shots.SHOTS.glob("*.png")}
    assert len(table) == sum(len(s.images) for s in shots.SCREENSHOTS), "an image is in two entries of the table"
    assert not on_disk - set(table), f"images no command of the table makes: {sorted(on_disk - set(table))}"
    assert not set(table) - on_disk, f"table entries without their image: {sorted(set(table) - on_disk)}"
    rows = shots.manifest_rows()
    assert set(rows) == set(table), f"MANIFEST.md lists {sorted(set(rows) ^ set(table))} differently from the table"
    stale = [
        image
        for image, (command, commit, _) in rows.items()
        if command != shots.shown(table[image]) or commit == shots.NOT_MADE
    ]
    assert not stale, f"not made by the table's command (run python benchmarks/docs_assets.py --screenshots): {stale}"


def test_every_image_the_readme_and_the_guide_show_is_in_the_table() -> None:
    table = shots.by_image()
    documents = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    referenced = {(d.name, m.group(1)) for d in documents for m in REFERENCE.finditer(d.read_text())}
    assert {image for _, image in referenced} >= {"viser_panel.png", "rerun_recording_explain.png"}
    missing = sorted((doc, image) for doc, image in referenced if image not in table)
    assert not missing, f"images the docs show that no command of the table makes: {missing}"


@pytest.mark.skipif(
    shutil.which("chromium") is None and shutil.which("chromium-browser") is None,
    reason="Debian's chromium is not on PATH (apt-get install chromium; CI installs it)",
)
@pytest.mark.parametrize("image", sorted(CHEAPEST))
def test_the_cheapest_screenshots_of_the_table_are_made(image, tmp_path) -> None:
    pytest.importorskip("playwright.sync_api", reason="the Python playwright package is not installed")
    shot = shots.by_image()[image]
    assert shot.images == (image,) and len(shot.commands) == 1, "the check runs one command that makes one image"
    extra = CHEAPEST[image]
    if extra[-1] == "--rrd":
        from pemviz import cli

        small = tmp_path / "run" / "small.rrd"
        small.parent.mkdir()
        assert cli.main([*SMALL_RUN, "--save", str(small)]) == 0
        extra = (*extra, str(small))
    (png,) = shots.run_shot(shot, out=tmp_path, extra=extra, timeout=240, quiet=True)
    assert png == tmp_path / image and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert not list(tmp_path.glob("*.partial.png"))
