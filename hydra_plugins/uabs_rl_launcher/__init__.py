"""The Hydra door of uabs_rl's parallel launcher (``hydra/launcher=local_parallel``):
Hydra's joblib launcher, whose sweep a Ctrl-C stops with every running job saved
(:mod:`uabs_rl.cli.parallel`). Hydra imports every module under ``hydra_plugins`` when
any Hydra app starts: this one stays light, and defines nothing without the joblib
launcher (the ``parallel`` extra)."""

from __future__ import annotations

from pathlib import Path

try:
    from hydra_plugins.hydra_joblib_launcher.joblib_launcher import JoblibLauncher
except ImportError:  # the parallel extra is not installed: local_parallel says so
    JoblibLauncher = None

if JoblibLauncher is not None:

    class StoppableJoblibLauncher(JoblibLauncher):
        """Hydra's joblib launcher; a signal stops its sweep after the running jobs
        saved (conf/hydra/launcher/local_parallel.yaml)."""

        def launch(self, job_overrides, initial_job_idx):
            from uabs_rl.cli.parallel import launch_stoppable, worker_start

            # each worker out of the terminal's process group, ignoring the signals
            # between jobs (joblib passes it on to loky's executor)
            self.joblib["initializer"] = worker_start
            sweep_dir = Path(str(self.config.hydra.sweep.dir)).absolute()
            return launch_stoppable(lambda: super(StoppableJoblibLauncher, self).launch(
                job_overrides, initial_job_idx), sweep_dir)
