"""What a job needs, opened once per process: settings, database, blob folder, executor and job runner."""
from __future__ import annotations

import logging
from dataclasses import dataclass

from ..config import Settings
from ..storage import registry
from ..storage.blobs import BlobStore
from ..storage.database import Database, blob_is_referenced, referenced_blobs
from .decoding import DecodePool
from .executors import Executor, make_executor
from .runner import JobRunner

log = logging.getLogger("learnest.jobs")


@dataclass
class Services:
    """What a job needs, opened once per process (`open_services`)."""

    settings: Settings
    db: Database
    blobs: BlobStore
    executor: Executor
    runner: JobRunner
    decoder: DecodePool
    owns_executor: bool = True
    owns_decoder: bool = True

    def close(self) -> None:
        """Shut the runner down, the executor and the upload decoders too if these services created them, and
        dispose the database."""
        self.runner.shutdown()
        if self.owns_executor:
            self.executor.shutdown()
        if self.owns_decoder:
            self.decoder.shutdown()
        self.db.dispose()


def open_services(settings: Settings, executor: Executor | None = None,
                  decoder: DecodePool | None = None) -> Services:
    """Migrate the database, open the blob folder and the executor, fail jobs of crashed servers.
    ``executor``, ``decoder``: already running ones to share (not shut down by `Services.close`); None: made
    from the settings (the decoder starts its processes on the first upload)."""
    settings.home.mkdir(parents=True, exist_ok=True)
    db = Database(settings.url)
    db.migrate()
    blobs = BlobStore(settings.home / "blobs")
    runner = JobRunner(db, cancel_grace_s=settings.cancel_grace_s, stall_s=settings.job_stall_s,
                       max_queued=settings.max_queued_jobs)
    runner.on_stale.append(registry.fail_versions_of_jobs)
    runner.start()
    owns = executor is None
    executor = executor or make_executor(settings.dask_address, settings.pool_workers)
    owns_decoder = decoder is None
    decoder = decoder or DecodePool(settings.decode_workers, settings.decode_queue, settings.decode_timeout_s)
    return Services(settings, db, blobs, executor, runner, decoder, owns_executor=owns, owns_decoder=owns_decoder)


def sweep_orphan_blobs(db: Database, blobs: BlobStore) -> list[str]:
    """Delete blobs no row names: a crash between a blob's write and its row's commit leaves one behind.
    Safe beside a running server: writers hold the store's shared lock until their row is committed,
    and `collect` checks each candidate again under the exclusive lock."""
    referenced = referenced_blobs(db)
    removed = blobs.collect([sha for sha in blobs.all_blobs() if sha not in referenced],
                            lambda sha: blob_is_referenced(db, sha))
    if removed:
        log.warning("removed %d orphaned blob(s) left by an interrupted write", len(removed))
    return removed
