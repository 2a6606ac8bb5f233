"""Sweep bookkeeping: a summary line per job at the end of a Hydra multirun."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from fusion_depth.runner.record import METRICS_FILE, read_finished
from fusion_depth.runner.run_folder import FAILURE_FILE
from fusion_depth.utils.atomic import write_json_atomic

log = logging.getLogger(__name__)


def summarize_sweep(sweep_dir: str | Path) -> list[dict]:
    """Status of every job directory (one holding ``.hydra/overrides.yaml``) in a sweep."""
    jobs = []
    for overrides_file in sorted(
        Path(sweep_dir).glob("*/.hydra/overrides.yaml"),
        key=lambda p: (len(p.parent.parent.name), p.parent.parent.name),
    ):
        job_dir = overrides_file.parent.parent
        overrides = list(OmegaConf.load(overrides_file))
        finished = read_finished(job_dir)  # a run that trained no step is not done
        if finished is not None:
            jobs.append(
                {
                    "dir": str(job_dir),
                    "overrides": overrides,
                    "status": "ok",
                    "rmse": finished.test.get("rmse"),
                }
            )
        elif (job_dir / FAILURE_FILE).is_file():
            failure = json.loads((job_dir / FAILURE_FILE).read_text())
            jobs.append(
                {
                    "dir": str(job_dir),
                    "overrides": overrides,
                    "status": "failed",
                    "error": failure["error"],
                }
            )
        else:
            jobs.append({"dir": str(job_dir), "overrides": overrides, "status": "incomplete"})
    return jobs


class SweepSummary(Callback):
    """Prints one line per job (ok / failed with the error) and exits non-zero on failure.

    It reads the job directories rather than in-memory results so it works with every
    launcher, including those that run jobs in other processes.
    """

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        jobs = summarize_sweep(sweep_dir)
        write_json_atomic(sweep_dir / "sweep_summary.json", jobs)
        lines = [f"Sweep summary ({sweep_dir}):"]
        for job in jobs:
            what = " ".join(job["overrides"]) or "(defaults)"
            if job["status"] == "ok":
                detail = f"test rmse {job['rmse']:.4f}" if job.get("rmse") is not None else ""
            else:
                detail = job.get("error", f"no {METRICS_FILE}: interrupted?")
            lines.append(f"  {job['status']:<10} {what}  {detail}")
        bad = [j for j in jobs if j["status"] != "ok"]
        lines.append(f"{len(jobs) - len(bad)} ok, {len(bad)} failed or incomplete")
        print("\n".join(lines), flush=True)
        if bad:
            raise SystemExit(1)
