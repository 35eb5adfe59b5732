"""Every image of ``assets/screenshots/`` (the README's and the user guide's), with the command that makes it from the
current code: :data:`SCREENSHOTS`, one table. ``python benchmarks/docs_assets.py --screenshots`` runs every command of
the table (``--only NAME ...``: the entries that make those images), checks that each wrote its images, and rewrites
``assets/screenshots/MANIFEST.md`` from the table: for every image its command, the commit and the date that made it.

A command is run from the repository root as a list of words (no shell): leading ``NAME=value`` words are environment
variables, ``python`` is this interpreter, ``pemviz`` is ``python -m pemviz.cli``, ``$TMP`` is a temporary folder
(removed afterwards) and a word beginning with ``assets/screenshots/`` is a path in the output folder (so that a test
can make an image elsewhere: ``tests/project/test_screenshot_manifest.py``). Every command needs Debian's ``chromium``;
the whole table takes about 5 min on the 2-core machine.
"""

from __future__ import annotations

import datetime
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHOTS = REPO / "assets" / "screenshots"
MANIFEST = SHOTS / "MANIFEST.md"
PREFIX = "assets/screenshots/"
TAB_SHOTS = tuple(
    f"panel_{scene}_{tab}.png"
    for scene in ("braking", "cut_in")
    for tab in ("live", "explain", "compare", "rollouts", "runs", "experiment")
)
"""What ``PEMVIZ_SCREENSHOTS=1`` writes in ``tests/app/test_app_tabs.py``: every tab after a tiny braking and cut-in
run."""


@dataclass(frozen=True)
class Shot:
    """Images of ``assets/screenshots/`` and the commands, run in order, that make them."""

    images: tuple[str, ...]
    commands: tuple[str, ...]


SCREENSHOTS: tuple[Shot, ...] = (
    Shot(("viser_panel.png",), ("python benchmarks/screenshot_panel.py --out assets/screenshots/viser_panel.png",)),
    Shot(
        ("panel_explain.png", "panel_live.png", "panel_scene.png"),
        (
            "python benchmarks/screenshot_panel.py --preset state-ce --k 10 --metric agm --set alpha=0.2 "
            "--set sigma=0.9 "
            "--width 1400 --height 900 --out assets/screenshots/panel_explain.png "
            "--live-out assets/screenshots/panel_live.png --scene-out assets/screenshots/panel_scene.png",
        ),
    ),
    Shot(
        ("panel_cut_in.png",),
        (
            "python benchmarks/screenshot_panel.py --scenario cut-in --set seed=1 --width 1400 --height 900 "
            "--out assets/screenshots/panel_cut_in.png",
        ),
    ),
    Shot(
        ("panel_compare.png",),
        ("PEMVIZ_SCREENSHOTS=1 python -m pytest -q -p no:cacheprovider tests/app/test_app_compare.py",),
    ),
    Shot(
        ("panel_odd.png",),
        ("PEMVIZ_SCREENSHOTS=1 python -m pytest -q -p no:cacheprovider tests/app/test_app_odd.py",),
    ),
    Shot(TAB_SHOTS, ("PEMVIZ_SCREENSHOTS=1 python -m pytest -q -p no:cacheprovider tests/app/test_app_tabs.py",)),
    Shot(
        ("rerun_recording.png",),
        ("python benchmarks/screenshot_recording.py --tab stages --out assets/screenshots/rerun_recording.png",),
    ),
    Shot(
        ("rerun_recording_step.png",),
        ("python benchmarks/screenshot_recording.py --tab rollouts --out assets/screenshots/rerun_recording_step.png",),
    ),
    Shot(
        ("rerun_recording_explain.png",),
        (
            "python benchmarks/screenshot_recording.py --tab explain --out "
            "assets/screenshots/rerun_recording_explain.png",
        ),
    ),
    Shot(
        ("rerun_recording_cut_in.png",),
        (
            "pemviz run --scenario cut-in --seed 1 --save $TMP/cut_in.rrd",
            "python benchmarks/screenshot_recording.py --rrd $TMP/cut_in.rrd --scenario cut-in --tab explain --step 18 "
            "--out assets/screenshots/rerun_recording_cut_in.png",
        ),
    ),
)
"""Every image of ``assets/screenshots/`` and the commands that make it. The recording screenshots without ``--rrd``
record ``pemviz run``'s defaults (seed 0) first, the same run each time."""


def by_image() -> dict[str, Shot]:
    """Each image's entry of :data:`SCREENSHOTS`."""
    return {image: shot for shot in SCREENSHOTS for image in shot.images}


def shown(shot: Shot) -> str:
    """The entry's commands as the manifest prints them."""
    return ", then ".join(f"`{c}`" for c in shot.commands)


def argv(command: str, out: Path, tmp: Path) -> tuple[list[str], dict[str, str]]:
    """(words to run, environment variables to add) of ``command`` (module docstring)."""
    words, env = shlex.split(command), {}
    while words and re.fullmatch(r"[A-Z_][A-Z0-9_]*=.*", words[0]):
        name, value = words.pop(0).split("=", 1)
        env[name] = value
    if words[0] == "python":
        words[:1] = [sys.executable]
    elif words[0] == "pemviz":
        words[:1] = [sys.executable, "-m", "pemviz.cli"]
    words = [str(out / w[len(PREFIX) :]) if w.startswith(PREFIX) else w.replace("$TMP", str(tmp)) for w in words]
    return words, env


def run_shot(
    shot: Shot, out: Path = SHOTS, extra: tuple[str, ...] = (), timeout: float | None = None, quiet: bool = False
) -> list[Path]:
    """Run ``shot``'s commands (``extra`` appended to the last one) writing into ``out``; the images written.

    Raises:
        RuntimeError: a command exited non-zero, or an image was not written by them (a test skipped: no chromium?).
    """
    paths = [out / image for image in shot.images]
    before = {p: p.stat().st_mtime_ns if p.exists() else None for p in paths}
    env = {
        **os.environ,
        "RERUN_ANALYTICS": "false",
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
    }
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="pemviz-shots-") as tmp:
        for i, command in enumerate(shot.commands):
            words, more = argv(command, out, Path(tmp))
            if i == len(shot.commands) - 1:
                words += list(extra)
                command = " ".join([command, *extra])
            if not quiet:
                print("+", command, flush=True)
            proc = subprocess.run(
                words, cwd=REPO, env={**env, **more}, timeout=timeout, capture_output=quiet, text=True
            )
            if proc.returncode != 0:
                tail = f"\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}" if quiet else ""
                raise RuntimeError(f"{command!r} exited {proc.returncode}{tail}")
    stale = [p.name for p in paths if not p.exists() or p.stat().st_mtime_ns == before[p] or p.stat().st_size == 0]
    if stale:
        raise RuntimeError(f"{', '.join(stale)} not written by {shown(shot)} (a skipped test: is chromium installed?)")
    return paths


def made_by() -> str:
    """The commit of the working tree (``git rev-parse --short HEAD``), "with uncommitted changes" when
    ``pemviz/`` or ``benchmarks/`` differ from it."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()

    commit = f"`{git('rev-parse', '--short', 'HEAD')}`"
    return commit + (" with uncommitted changes" if git("status", "--porcelain", "--", "pemviz", "benchmarks") else "")


ROW = re.compile(r"^\| `(?P<image>[^`]+\.png)` \| (?P<command>.*) \| (?P<commit>[^|]*) \| (?P<date>[^|]*) \|$")
NOT_MADE = "not yet made by this command"


def manifest_rows(path: Path = MANIFEST) -> dict[str, tuple[str, str, str]]:
    """The manifest's rows: image -> (command, commit, date), as written by :func:`write_manifest`."""
    if not path.exists():
        return {}
    return {
        m["image"]: (m["command"], m["commit"], m["date"]) for m in map(ROW.match, path.read_text().splitlines()) if m
    }


def write_manifest(made: dict[str, tuple[str, str]], path: Path = MANIFEST) -> None:
    """Rewrite the manifest from :data:`SCREENSHOTS`: an image in ``made`` (image -> (commit, date)) gets that, any
    other keeps its row's commit and date if its command is the same, else :data:`NOT_MADE`."""
    old = manifest_rows(path)
    lines = [
        "# Which code made each screenshot",
        "",
        "Written by `python benchmarks/docs_assets.py --screenshots` (the table `SCREENSHOTS` of",
        "`benchmarks/screenshots.py`), which runs every command below from the repository root and then rewrites",
        "this file; `--only NAME ...` remakes some. `$TMP` is a temporary folder. The commit is the code that made",
        'the image (`git rev-parse --short HEAD`; "with uncommitted changes" when `pemviz/` or `benchmarks/`',
        "differed from it). `tests/project/test_screenshot_manifest.py` checks that every image is in the table",
        "and here, and makes the cheapest panel and recording screenshots; it does not compare pixels.",
        "",
        "| image | command | commit | date |",
        "|---|---|---|---|",
    ]
    for shot in SCREENSHOTS:
        command = shown(shot)
        for image in shot.images:
            if image in made:
                commit, date = made[image]
            elif image in old and old[image][0] == command:
                commit, date = old[image][1:]
            else:
                commit, date = NOT_MADE, ""
            lines.append(f"| `{image}` | {command} | {commit} | {date} |")
    partial = path.with_name(path.name + ".partial")
    partial.write_text("\n".join(lines) + "\n")
    os.replace(partial, path)


def regenerate(only: list[str] | None = None) -> int:
    """Remake the images of :data:`SCREENSHOTS` (``only``: the entries making those images) and rewrite the manifest
    after each entry; 1 if a command failed (the others still run), else 0."""
    table = by_image()
    names = [n if n.endswith(".png") else n + ".png" for n in only or []]
    unknown = [n for n in names if n not in table]
    if unknown:
        raise SystemExit(f"not in the screenshot table: {', '.join(unknown)} (known: {', '.join(table)})")
    shots = [s for s in SCREENSHOTS if not names or set(s.images) & set(names)]
    commit, failed, t0 = made_by(), [], time.monotonic()
    for shot in shots:
        t = time.monotonic()
        try:
            run_shot(shot)
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            failed.append(shot)
            print(f"FAILED {', '.join(shot.images)}: {exc}", flush=True)
            continue
        date = datetime.date.today().isoformat()
        write_manifest({image: (commit, date) for image in shot.images})
        print(f"made   {', '.join(shot.images)} in {time.monotonic() - t:.0f} s", flush=True)
    write_manifest({})
    print(
        f"{len(shots) - len(failed)} of {len(shots)} entries made in {time.monotonic() - t0:.0f} s by {commit}; "
        f"{MANIFEST.relative_to(REPO)} rewritten",
        flush=True,
    )
    return 1 if failed else 0
