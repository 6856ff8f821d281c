"""The sweep's output folder: one sub-folder per computed cell, named by its content key.

Layout of ``DIR``::

    cells/<scene>_<map>_<sampler>_<key>/cell.json     status, inputs, where and how long it ran
    cells/<scene>_<map>_<sampler>_<key>/report.json   the cell's compare report (and its
                                                      index.html, CSV, EXR/PNG files)
    index.html, aggregate.json, aggregate.csv, heatmap_<sampler>.png

Only the process that runs the sweep writes here (workers return their report folder as a
zip archive), and a cell folder appears by an atomic rename once complete, so an
interrupted sweep leaves no half-written cell behind. A cell is *finished* when its
``cell.json`` says ``"ok"``; failed cells are stored too (with their error) and computed
again by the next run. Folders of keys no longer in the grid are left alone.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import zipfile

from .cells import CellResult
from .grid import Cell


class CellStore:
    """Cell folders under ``<out>/cells``."""

    def __init__(self, out: str):
        self.out = os.path.abspath(out)
        self.cells_dir = os.path.join(self.out, "cells")

    def folder(self, cell: Cell, key: str) -> str:
        return os.path.join(self.cells_dir, f"{cell.scene.name}_{cell.map.name}_{cell.sampler}_{key}")

    def _read(self, cell: Cell, key: str, name: str) -> dict | None:
        path = os.path.join(self.folder(cell, key), name)
        if not os.path.isfile(path):
            return None
        with open(path) as f:
            return json.load(f)

    def record(self, cell: Cell, key: str) -> dict | None:
        """The stored ``cell.json`` of ``cell`` at ``key``, or None."""
        return self._read(cell, key, "cell.json")

    def finished(self, cell: Cell, key: str) -> bool:
        record = self.record(cell, key)
        return record is not None and record.get("status") == "ok"

    def report(self, cell: Cell, key: str) -> dict | None:
        """The cell's compare ``report.json``, or None if it has none."""
        return self._read(cell, key, "report.json")

    def save(self, cell: Cell, key: str, inputs: dict, result: CellResult) -> dict:
        """Store a result (unpacking its archive); returns the ``cell.json`` record written."""
        final = self.folder(cell, key)
        partial = final + ".partial"
        shutil.rmtree(partial, ignore_errors=True)
        os.makedirs(partial)
        if result.archive is not None:
            with zipfile.ZipFile(io.BytesIO(result.archive)) as archive:
                archive.extractall(partial)
        record = {"status": result.status, "label": cell.label, "key": key, "inputs": inputs,
                  "error": result.error, "traceback": result.traceback,
                  "wall_time_s": result.wall_time_s, "host": result.host,
                  "drjit_threads": result.drjit_threads, "code_version": result.code_version}
        with open(os.path.join(partial, "cell.json"), "w") as f:
            json.dump(record, f, indent=1)
        shutil.rmtree(final, ignore_errors=True)
        os.rename(partial, final)
        return record
