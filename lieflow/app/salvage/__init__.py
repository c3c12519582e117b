"""Salvage a damaged trajectory file: keep every row that reads back, repair what has a copy,
and make the file resumable again.

A trajectory file (:mod:`lieflow.app.io`) whose bytes were damaged on disk — a process killed
while HDF5 rewrote a chunk, a file cut short by a full disk or a bad copy, flipped bits — is
refused by ``lieflow run --resume`` and by every reader. :func:`salvage` (``lieflow salvage
FILE``) rebuilds it from what still reads back:

1. The damaged file is only read (a file shorter than HDF5 recorded is read as if padded
   to its recorded length with bytes that fail every checksum they cover). Every
   dataset is read chunk by chunk, each chunk's Fletcher-32 checksum verified: a damaged
   chunk costs its rows only (at most 128 steps of one diagnostic, or 4 KiB of saved states:
   :data:`~lieflow.app.io._format.CHUNK_ROWS`), never the rows around it.
2. What has a copy is repaired from it: ``initial/W0`` from the saved state of step 0 (and
   that from ``W0``), a saved state's step from its time and back (``t = k h``), the step
   coordinate (``0..K``), a header attribute from the run's identity or configuration
   (``system``, ``scheme``, ``solver``, ``h``, ``save_every``, ``identity``,
   ``casimir_powers``); an attribute with no copy (``config_source``, the versions, ...) is
   set empty, and said so.
3. The restart point is a step ``k`` with a verified state and its energy and Casimirs
   intact: the later checkpoint slot whose SHA-256 digest matches (the run then continues bit
   for bit as if never stopped), or, only if neither is usable, the latest intact saved state
   (the run continues from it with a cold solver start: its later steps agree with an
   uninterrupted run to the solver's tolerance, not bit for bit), or step 0.
4. A new file is written with every row of steps ``0..k`` — the rows of damaged chunks as
   holes (``NaN``; ``-1`` solver updates), the saved states of lost steps left out — its
   checkpoint at ``k``, marked ``interrupted`` and with the attribute ``salvaged`` saying what
   was lost and repaired; ``lieflow run CONFIG --resume`` then continues it.

The damaged original is kept as ``FILE.damaged`` (or ``FILE.damaged.1``, ...) and the new file
takes its name only when it is complete, so a salvage that fails leaves the file as it was.

The package's modules, one concern each: ``_reading`` (the damaged file opened read-only,
padded where it was cut short, read chunk by chunk with checksums verified), ``_repairs``
(what it lost, from its copies: header attributes, step 0, the saved states' steps, the
restart point), ``_plan`` (what the rebuilt file holds), ``_rebuild`` (writing it) and
``_salvage`` (:func:`salvage` and its :class:`SalvageReport`).
"""

from __future__ import annotations

from ._salvage import SalvageReport, salvage

__all__ = ["SalvageReport", "salvage"]
