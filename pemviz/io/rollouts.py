"""Logged rollouts on disk: read and validate a rollout file (:func:`read_rollouts`). Bad input raises
:class:`~pemviz.io.rollout_format.RolloutFormatError` naming the file, the column, the rollout and the step."""

from __future__ import annotations

import os
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from pemviz.io.data import sha256_file
from pemviz.io.files import MAGIC
from pemviz.io.rollout_format import RolloutFormatError, existing_sidecar, read_sidecar
from pemviz.io.rollout_table import RolloutData, _Table

RECORDING_MAGIC = b"RRF"
"""The first bytes of a rerun recording (``.rrd``): ``RRF2`` today, ``RRF0`` / ``RRF1`` in older rerun versions."""


def check_not_a_recording(path: Path) -> None:
    """Refuse a rerun recording given where a rollout file is expected, saying how to write a rollout file.

    Raises:
        RolloutFormatError: ``path`` ends in ``.rrd`` or starts with :data:`RECORDING_MAGIC`."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(RECORDING_MAGIC))
    except OSError:
        head = b""
    if path.suffix.lower() == ".rrd" or head == RECORDING_MAGIC:
        raise RolloutFormatError(
            f"{path}: a rerun recording, not a rollout file; `pemviz estimate` reads the Parquet rollout file that "
            "`pemviz run --save-rollouts NAME.parquet` writes (with its sidecar NAME.rollouts.json), and `rerun "
            f"{path.name}` opens the recording"
        )


WRITTEN_BY = "`pemviz run --save-rollouts NAME.parquet`"
"""The command that writes rollout files, as the error messages name it."""


def check_parquet_magic(path: Path) -> None:
    """Refuse a file that does not start as a Parquet file does (:data:`pemviz.io.files.MAGIC`: ``PAR1``; an empty one
    too), before its sidecar is looked for: a text file or a CSV given by mistake is named as such, not as a rollout
    file without a sidecar.

    Raises:
        RolloutFormatError: the first four bytes are not ``PAR1``."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as exc:
        raise RolloutFormatError(f"{path}: cannot be read ({exc.strerror})") from None
    if head != MAGIC[".parquet"]:
        found = "an empty file" if not head else f"it starts with {head!r}"
        raise RolloutFormatError(
            f"{path}: not a Parquet file ({found}); `pemviz estimate` reads the Parquet rollout file that {WRITTEN_BY} "
            "writes"
        )


def read_rollouts(path: str | os.PathLike[str]) -> RolloutData:
    """Read and validate a rollout file and its sidecar.

    Returns:
        :class:`RolloutData`: observations [N, T, F], detected [N, T, M], optional salient [N, T, 11] and errors
        [N, T, M, D], log_p / log_q [N, T] (nats).
    Raises:
        FileNotFoundError: no such file.
        RolloutFormatError: the sidecar or the table breaks the format (module docstring); the message
            names the column and the rollout and step."""
    p = Path(path)
    if p.is_dir():
        raise RolloutFormatError(f"{p}: a folder, not a rollout file; give the NAME.parquet that {WRITTEN_BY} writes")
    if not p.is_file():
        raise FileNotFoundError(f"rollout file {p} not found")
    check_not_a_recording(p)
    check_parquet_magic(p)
    meta = read_sidecar(p)
    try:
        table = pq.read_table(p)
    except (pa.ArrowException, OSError) as exc:
        raise RolloutFormatError(f"{p}: not a readable Parquet file ({exc})") from None
    data = _Table(table, meta, str(p)).parse(p)
    if meta.table_sha256 is not None and sha256_file(p) != meta.table_sha256:
        raise RolloutFormatError(
            f"{p}: the table is not the one its sidecar {existing_sidecar(p).name} was written with (table_sha256 "
            "differs): an interrupted or concurrent write; write it again (or drop table_sha256 from the sidecar "
            "if the table was changed on purpose)"
        )
    return data
