"""Streaming Parquet tables: rows are buffered per column and flushed in batches, so a
long run keeps memory flat. Written with pyarrow into the run's staging folder (the
folder is renamed into place only when the run completes, see :class:`v2v.io.atomic.RunFolder`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq


class ParquetStream:
    """Append rows (dicts of scalars) or column batches; flush every ``batch_rows`` rows."""

    def __init__(self, path: Path, batch_rows: int = 50_000):
        self.path = Path(path)
        self.batch_rows = batch_rows
        self._cols: dict[str, list[Any]] = {}
        self._n = 0
        self._writer: pq.ParquetWriter | None = None
        self._schema: pa.Schema | None = None
        self.rows_written = 0

    def append(self, row: dict[str, Any]) -> None:
        if not self._cols:
            self._cols = {k: [] for k in row}
        for k, v in row.items():
            self._cols[k].append(v)
        self._n += 1
        if self._n >= self.batch_rows:
            self.flush()

    def extend(self, columns: dict[str, list[Any]]) -> None:
        """Append a batch given as columns of equal length."""
        if not columns:
            return
        n = len(next(iter(columns.values())))
        if not self._cols:
            self._cols = {k: [] for k in columns}
        for k, v in columns.items():
            self._cols[k].extend(v)
        self._n += n
        if self._n >= self.batch_rows:
            self.flush()

    def flush(self) -> None:
        if self._n == 0:
            return
        table = pa.table(self._cols) if self._schema is None else pa.table(self._cols, schema=self._schema)
        if self._writer is None:
            self._schema = table.schema
            self._writer = pq.ParquetWriter(self.path, self._schema, compression="zstd")
        self._writer.write_table(table)
        self.rows_written += self._n
        self._cols = {k: [] for k in self._cols}
        self._n = 0

    def close(self, empty_schema: pa.Schema | None = None) -> None:
        self.flush()
        if self._writer is not None:
            self._writer.close()
        elif empty_schema is not None:
            pq.write_table(empty_schema.empty_table(), self.path)
