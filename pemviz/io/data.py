"""The KITTI salient-variable files: find them, fetch them, load and validate them.

The files are third-party data (KITTI object detection, CC BY-NC-SA 3.0; YOLOv3 detections matched to ground truth
by Innes & Ramamoorthy), never shipped; they are found in ``$PEMVIZ_DATA_DIR``, ``<repository
root>/../shared/data/kitti-salient``, then the user cache (``$XDG_CACHE_HOME/pemviz/kitti-salient``), where ``pemviz
data fetch`` (:func:`fetch`) downloads them and checks their SHA-256.

Input columns (11): class, truncation, occlusion, alpha, dim_w, dim_l, dim_h, loc_x, loc_y, loc_z, rot_y (KITTI
camera frame: metres, radians; the box dimensions are KITTI's height, width, length in that order). Label columns
(9): detected, the detector's box cx, cy, w, h and its error (detector minus ground truth) in pixels
(:func:`load_salient_label_table`)."""

from __future__ import annotations

import hashlib
import math
import os
import urllib.error
import urllib.request
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pemviz.core.files import atomic_write, repo_root
from pemviz.pem.encoding import INPUT_COLUMNS

__all__ = [
    "DATA_DIR_ENV",
    "FILE_SHA256",
    "INPUTS_FILE",
    "LABELS_FILE",
    "LABEL_COLUMNS",
    "ORIGIN_BASE_URL",
    "ChecksumError",
    "DataError",
    "DataFormatError",
    "DataNotFoundError",
    "SalientData",
    "candidate_data_dirs",
    "fetch",
    "find_data_dir",
    "load_salient_data",
    "load_salient_inputs",
    "load_salient_label_table",
    "sha256_file",
    "user_cache_dir",
]

DATA_DIR_ENV = "PEMVIZ_DATA_DIR"
"""Environment variable naming a folder that holds the salient files (searched first)."""

INPUTS_FILE = "salient_inputs_no_miscUnknown.txt"
LABELS_FILE = "salient_labels_no_miscUnknown.txt"
INPUTS_FILE_ALL = "salient_inputs.txt"
LABELS_FILE_ALL = "salient_labels.txt"

FILE_SHA256: dict[str, str] = {
    INPUTS_FILE: "fba2f0c9da60da52430d65ece37647bd02d912c2f21f8ad4e00240f80b66481e",
    LABELS_FILE: "64e0974be03f5ffd1a50151f7333bb0c2b90079bb7dd49b5e10a5e383aacc4bb",
    INPUTS_FILE_ALL: "c70c8ffcc281d719e5fceea0992496c59fd476e8b2c79ac5a56d7ebb83d56e3b",
    LABELS_FILE_ALL: "09ca60fdff3cd9a8410f49fbfd7d45cc81f5b38c7cce5b496a795fc34324b8b7",
}
"""SHA-256 of the four files at the origin commit."""

ORIGIN_REPO = "craigiedon/PyTorch-YOLOv3-kitti"
ORIGIN_COMMIT = "0544b1899417eaca808f2094853262a656f0f34d"
ORIGIN_BASE_URL = f"https://raw.githubusercontent.com/{ORIGIN_REPO}/{ORIGIN_COMMIT}/salient_dataset"
"""Public origin of the files; ``<ORIGIN_BASE_URL>/<file name>``."""

LABEL_COLUMNS = ("detected", "bbox_cx", "bbox_cy", "bbox_w", "bbox_h", "err_cx", "err_cy", "err_w", "err_h")

FETCH_COMMAND = "pemviz data fetch"


class DataError(Exception):
    """Base class of pemviz's data errors."""


class DataNotFoundError(DataError, FileNotFoundError):
    """The salient files are in none of the searched places."""


class DataFormatError(DataError, ValueError):
    """A salient file is malformed (column count, label value, NaN ...); the message names file and line."""


class ChecksumError(DataError, ValueError):
    """A downloaded file's SHA-256 differs from the expected one (nothing is written)."""


# --------------------------------------------------------------------------------------------- locate


def user_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/pemviz/kitti-salient``, default ``~/.cache/pemviz/kitti-salient``."""
    base = os.environ.get("XDG_CACHE_HOME") or ""
    root = Path(base) if base.strip() else Path.home() / ".cache"
    return root / "pemviz" / "kitti-salient"


def candidate_data_dirs() -> list[tuple[str, Path | None]]:
    """The searched places, in order, as ``(description, folder)``; folder is None when the env var is unset."""
    env = os.environ.get(DATA_DIR_ENV)
    return [
        (f"${DATA_DIR_ENV}", Path(env).expanduser() if env else None),
        ("beside the repository", repo_root().parent / "shared" / "data" / "kitti-salient"),
        ("user cache", user_cache_dir()),
    ]


def find_data_dir(required: Iterable[str] = (INPUTS_FILE, LABELS_FILE)) -> Path:
    """The first searched folder that holds every ``required`` file.

    Raises:
        DataNotFoundError: no folder holds them; the message lists every place searched, why each failed,
            and the fetch command."""
    required = tuple(required)
    reasons: list[str] = []
    for i, (what, folder) in enumerate(candidate_data_dirs(), start=1):
        if folder is None:
            reasons.append(f"  {i}. {what}: not set")
            continue
        if not folder.is_dir():
            reasons.append(f"  {i}. {what}: {folder} (no such folder)")
            continue
        missing = [name for name in required if not (folder / name).is_file()]
        if not missing:
            return folder
        reasons.append(f"  {i}. {what}: {folder} (missing {', '.join(missing)})")
    raise DataNotFoundError(
        "KITTI salient files not found ("
        + ", ".join(required)
        + "). Searched, in order:\n"
        + "\n".join(reasons)
        + f"\nRun `{FETCH_COMMAND}` to download them into {user_cache_dir()} "
        f"(or set ${DATA_DIR_ENV} to a folder that holds them)."
    )


# ---------------------------------------------------------------------------------------------- fetch


def sha256_file(path: str | os.PathLike[str]) -> str:
    """Hex SHA-256 of a file, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def fetch(
    dest: str | os.PathLike[str] | None = None,
    base_url: str = ORIGIN_BASE_URL,
    *,
    files: Iterable[str] | None = None,
    force: bool = False,
    timeout_s: float = 60.0,
    on_file: Callable[[str, str], None] | None = None,
) -> Path:
    """Download the salient files into ``dest`` (default: :func:`user_cache_dir`) and check their SHA-256; a file
    replaces its target only when its checksum matches :data:`FILE_SHA256`, and one already present with the right
    checksum is kept (unless ``force``).

    Args:
        dest: target folder (created if needed).
        base_url: folder URL (``<base_url>/<name>``); default: craigiedon/PyTorch-YOLOv3-kitti at commit 0544b18,
            ``salient_dataset/``.
        files: names to fetch (default: all four of :data:`FILE_SHA256`).
        force: download even if a file with the right checksum is present.
        timeout_s: socket timeout per request, seconds.
        on_file: called as ``on_file(name, status)`` with status ``"present"`` or ``"downloaded"``.

    Returns:
        The destination folder.

    Raises:
        ChecksumError: a downloaded file has the wrong SHA-256 (it is deleted).
        DataError: a download failed (HTTP error, unreachable host); message names the URL.
        ValueError: a name in ``files`` is not one of the known files."""
    names = tuple(FILE_SHA256) if files is None else tuple(files)
    unknown = [n for n in names if n not in FILE_SHA256]
    if unknown:
        raise ValueError(f"unknown salient file(s) {unknown}; known: {sorted(FILE_SHA256)}")
    folder = Path(dest).expanduser() if dest is not None else user_cache_dir()
    created = [d for d in (folder, *folder.parents) if not d.exists()]  # deepest first
    folder.mkdir(parents=True, exist_ok=True)
    try:
        _fetch_into(folder, names, base_url.rstrip("/"), force, timeout_s, on_file)
    except BaseException:
        for d in created:  # a failed fetch leaves no empty folder behind
            try:
                d.rmdir()
            except OSError:
                break
        raise
    return folder


def _fetch_into(
    folder: Path,
    names: tuple[str, ...],
    base: str,
    force: bool,
    timeout_s: float,
    on_file: Callable[[str, str], None] | None,
) -> None:
    """The download loop of :func:`fetch` (same errors)."""
    for name in names:
        target = folder / name
        expected = FILE_SHA256[name]
        if not force and target.is_file() and sha256_file(target) == expected:
            if on_file:
                on_file(name, "present")
            continue
        url = f"{base}/{name}"

        def download(tmp: str, url: str = url, expected: str = expected, target: Path = target) -> None:
            digest = hashlib.sha256()
            with open(tmp, "wb") as out:
                try:
                    with urllib.request.urlopen(url, timeout=timeout_s) as response:  # noqa: S310 (https/http only)
                        for chunk in iter(lambda: response.read(1 << 16), b""):
                            digest.update(chunk)
                            out.write(chunk)
                except (urllib.error.URLError, OSError) as exc:
                    raise DataError(f"download of {url} failed: {exc}") from exc
            got = digest.hexdigest()
            if got != expected:
                raise ChecksumError(
                    f"{url}: SHA-256 {got} differs from the expected {expected}; "
                    f"the file was not written to {target}"
                )

        atomic_write(target, download)
        if on_file:
            on_file(name, "downloaded")


# ----------------------------------------------------------------------------------------------- load


def _parse_table(path: Path, n_columns: int) -> np.ndarray:
    """Parse a whitespace table with one optional ``#`` header line into float64 ``[N, n_columns]``.

    Raises:
        DataFormatError: wrong column count, a non-number, NaN or infinity; names file and line (1-based)."""
    rows: list[list[float]] = []
    with open(path, encoding="utf-8") as fh:
        for line_no, line in enumerate(fh, start=1):
            text = line.strip()
            if not text or (line_no == 1 and text.startswith("#")):
                continue
            fields = text.split()
            if len(fields) != n_columns:
                raise DataFormatError(f"{path}, line {line_no}: {len(fields)} columns, expected {n_columns}")
            try:
                values = [float(f) for f in fields]
            except ValueError:
                raise DataFormatError(f"{path}, line {line_no}: not a number in {text!r}") from None
            if not all(math.isfinite(v) for v in values):
                raise DataFormatError(f"{path}, line {line_no}: NaN or infinite value in {text!r}")
            rows.append(values)
    if not rows:
        raise DataFormatError(f"{path}: no data rows")
    return np.asarray(rows, dtype=np.float64)


def load_salient_inputs(path: str | os.PathLike[str]) -> np.ndarray:
    """Salient inputs, float64 ``[N, 11]`` (columns :data:`~pemviz.pem.encoding.INPUT_COLUMNS`; metres, radians).

    Raises:
        DataFormatError: wrong column count, non-number or NaN (names file and line).
        FileNotFoundError: ``path`` does not exist."""
    return _parse_table(Path(path), len(INPUT_COLUMNS))


def load_salient_label_table(path: str | os.PathLike[str]) -> np.ndarray:
    """The whole label file, float64 ``[N, 9]`` (columns :data:`LABEL_COLUMNS`; pixels of the original image):
    detected (0 or 1), the *detector's* box (centre x, centre y, width, height) and its error, detector minus ground
    truth (the authors' ``saveSalientDataset.py``), so the ground-truth box is ``box - err``; a missed obstacle's
    row is all zero.

    Raises:
        DataFormatError: wrong column count (9 expected), non-number, NaN, a label not in {0, 1}, or a detected row
            whose detected or ground-truth box has a width or height <= 0 (names file and line).
        FileNotFoundError: ``path`` does not exist."""
    path = Path(path)
    table = _parse_table(path, len(LABEL_COLUMNS))
    detected = table[:, 0]
    bad = np.flatnonzero((detected != 0.0) & (detected != 1.0))
    if bad.size:
        line_no = _data_line_numbers(path)[bad[0]]
        raise DataFormatError(f"{path}, line {line_no}: label {detected[bad[0]]:g} is not 0 or 1 (column 0, detected)")
    size = np.concatenate([table[:, 3:5], table[:, 3:5] - table[:, 7:9]], axis=1)  # detected w, h; true w, h
    bad = np.flatnonzero((detected == 1.0) & np.any(size <= 0.0, axis=1))
    if bad.size:
        line_no = _data_line_numbers(path)[bad[0]]
        raise DataFormatError(
            f"{path}, line {line_no}: a detected obstacle's box (w, h) and ground-truth box (w - err w, h - err h) "
            f"must be > 0 pixels, got {size[bad[0]].tolist()}"
        )
    return table


def _data_line_numbers(path: Path) -> list[int]:
    """1-based line numbers of the data rows of a file (header and blank lines skipped)."""
    out = []
    with open(path, encoding="utf-8") as fh:
        for line_no, line in enumerate(fh, start=1):
            text = line.strip()
            if text and not (line_no == 1 and text.startswith("#")):
                out.append(line_no)
    return out


@dataclass(frozen=True)
class SalientData:
    """The salient dataset: ``inputs`` float64 ``[N, 11]``, ``labels`` float64 ``[N]`` in {0, 1} (detected), and the
    whole label file ``label_table`` float64 ``[N, 9]`` (:func:`load_salient_label_table`: boxes and box errors)."""

    inputs: np.ndarray
    labels: np.ndarray
    inputs_path: Path
    labels_path: Path
    label_table: np.ndarray

    def __len__(self) -> int:
        return int(self.labels.shape[0])


def load_salient_data(
    data_dir: str | os.PathLike[str] | None = None, *, with_misc_unknown: bool = False
) -> SalientData:
    """Load inputs and labels (default: the ``no_miscUnknown`` files the paper trains on, 37,498 rows).

    Args:
        data_dir: folder holding the files; default :func:`find_data_dir`.
        with_misc_unknown: load ``salient_inputs.txt`` / ``salient_labels.txt`` (with class Misc and
            unknown occlusion) instead.

    Raises:
        DataNotFoundError: ``data_dir`` is None and the files are in no searched place.
        DataFormatError: a malformed file, or inputs and labels of different lengths."""
    names = (INPUTS_FILE_ALL, LABELS_FILE_ALL) if with_misc_unknown else (INPUTS_FILE, LABELS_FILE)
    folder = find_data_dir(names) if data_dir is None else Path(data_dir)
    inputs_path, labels_path = folder / names[0], folder / names[1]
    inputs = load_salient_inputs(inputs_path)
    table = load_salient_label_table(labels_path)
    if inputs.shape[0] != table.shape[0]:
        raise DataFormatError(
            f"{inputs_path} has {inputs.shape[0]} rows but {labels_path} has {table.shape[0]}; they must match"
        )
    return SalientData(
        inputs=inputs,
        labels=np.ascontiguousarray(table[:, 0]),
        inputs_path=inputs_path,
        labels_path=labels_path,
        label_table=table,
    )
