"""Independent studies of a sweep run as Ray tasks (`tiltfit stability --cluster auto|ADDRESS`).

Each study of `tiltfit.experiments.stability` is a function `study(cfg, log) -> Study` whose every noise draw is seeded
from `cfg.seed`, so it gives the same rows, findings and figure wherever it runs. `run_studies` runs them
here one after another, or as one Ray task each through `renderer.tracing.distributed.imap_on_cluster` (the
configuration shipped once), and hands them back in the order asked for, each as soon as it and all
before it are done; the caller writes the outputs exactly as for a serial run.

Spread and limits: the studies are the unit of work, so a run uses at most as many CPUs as it has studies
(five) and lasts at least as long as its slowest study; a study's own progress lines stay in its worker (the
driver logs when each is done). On N machines (`ray start --head` on one, `ray start --address HEAD:6379` on
the others, `--cluster HEAD:6379` here) every node needs this package importable (installed, or the
worktree on PYTHONPATH); what travels is the configuration (a few hundred bytes) out and each Study back
(its rows and a matplotlib figure, tens of KB).
"""
from __future__ import annotations

import pickle

import torch

from camio.progress import RunLog


def run_studies(studies: dict, names, cfg, log, cluster: str | None = None):
    """Yield `(name, study)` for each of `names`, in that order.

    Args:
        studies: {name: function(cfg, log) -> Study}; module-level functions (workers import them by name).
        names: which to run, in order.
        cfg: the run's configuration (seeds included), passed to every study.
        log: the driver's RunLog; studies run here log through it.
        cluster: None (here, one after another), or `auto` / a Ray address (one task per study, each with
            the driver's torch thread count).
    Raises:
        ImportError, ConnectionError: from `renderer.tracing.distributed` when the cluster cannot be used.
    """
    names = list(names)
    if cluster is None:
        for name in names:
            log(f"{name}: start")
            yield name, studies[name](cfg, log)
        return
    from renderer.tracing.distributed import cluster_session, imap_on_cluster

    threads = torch.get_num_threads()
    jobs = [studies[name] for name in names]
    with cluster_session(cluster):
        log(f"{', '.join(names)}: started as Ray tasks (cluster {cluster})")
        for i, study in imap_on_cluster(_study_task, jobs, cluster, shared=(cfg, threads), threads=threads):
            yield names[i], pickle.loads(study)


def _study_task(shared, study) -> bytes:
    """One task: `study(cfg, log)` with the driver's thread count for torch and OpenCV, progress muted.
    Returned pickled: Ray would hand numpy arrays back read-only, which the figure's own arrays must not be."""
    cfg, threads = shared
    try:
        import cv2

        cv2.setNumThreads(threads)
    except ImportError:
        pass
    return pickle.dumps(study(cfg, RunLog("stability", enabled=False)))
