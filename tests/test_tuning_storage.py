"""``train.py -optimize`` with shared Optuna storage: two worker processes on one journal file, one study (docs/scale.md)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import optuna
from optuna.storages.journal._storage import JournalOperation
from optuna.trial import TrialState

from sb3_pearl.zoo import train
from tests.conftest import run_in_process

ROOT = Path(__file__).resolve().parent.parent
ENV_ID = "SafePointGoalMeta-v0"
N_TRIALS = 2  # per worker


def test_two_workers_share_one_study_through_a_journal_file(tmp_path: Path) -> None:
    journal, study_name = tmp_path / "tuning" / "study.log", "pearlplus-safe-point"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    workers = [
        subprocess.Popen(
            [sys.executable, str(ROOT / "train.py"), "--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / f"w{seed}")]
            + ["-n", "300", "--n-trials", str(N_TRIALS), "-optimize", "--no-optim-plots", "--num-threads", "1"]
            + ["--storage", str(journal), "--study-name", study_name, "--seed", str(seed)],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for seed in (1, 2)  # one seed per worker, else both samplers propose the same parameters
    ]
    outputs = [worker.communicate(timeout=240)[0] for worker in workers]
    for worker, output in zip(workers, outputs):
        assert worker.returncode == 0, output[-3000:]

    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(journal)))
    study = optuna.load_study(study_name=study_name, storage=storage)
    trials = study.get_trials(deepcopy=False)
    assert len(trials) == 2 * N_TRIALS and sorted(t.number for t in trials) == list(range(2 * N_TRIALS))
    assert all(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in trials)
    assert "prior_coef" in trials[0].params  # the PEARL+ sampler
    # which process created each trial: the journal's worker ids are "<uuid of the process's storage>-<thread id>"
    with open(journal) as file:
        creators = [op["worker_id"][:36] for op in map(json.loads, file) if op["op_code"] == JournalOperation.CREATE_TRIAL]
    assert len(creators) == 2 * N_TRIALS and len(set(creators)) == 2
    assert all(creators.count(worker) == N_TRIALS for worker in set(creators))
    # the worker that finished last counted the other's trials too; each kept its own log folder
    finished = [int(re.search(r"Number of finished trials:\s+(\d+)", output).group(1)) for output in outputs]
    assert max(finished) == 2 * N_TRIALS and min(finished) >= N_TRIALS
    assert all((tmp_path / f"w{seed}" / "pearlplus").is_dir() for seed in (1, 2))

    # a trial of the shared study, by index, trains with its parameters (trial 0 included: rl_zoo3 alone skips it)
    replay = run_in_process(  # train.py's entry point in this process
        train,
        *("--algo", "pearlplus", "--env", ENV_ID, "-f", str(tmp_path / "trial0"), "-n", "300", "--num-threads", "1"),
        *("--eval-freq", "-1", "--storage", str(journal), "--study-name", study_name, "--trial-id", "0"),
        check=False,
    )
    assert replay.returncode == 0, replay.stdout[-3000:] + replay.stderr[-3000:]
    assert "Loading from Optuna study" in replay.stdout
    assert f"('prior_coef', {trials[0].params['prior_coef']})" in replay.stdout
