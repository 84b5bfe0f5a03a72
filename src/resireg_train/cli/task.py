"""Deprecated: the Hydra job wrapper of the CLIs moved to :mod:`resireg_train.cli.job`. This module re-exports its names, with a
``DeprecationWarning``, for one release."""

from resireg.deprecation import moved

__getattr__ = moved(
    "resireg_train.cli.task",
    {
        "CONFIG_DIR": "resireg_train.cli.job",
        "RUN_ID": "resireg_train.cli.job",
        "LOCK_FILE": "resireg_train.cli.job",
        "JobFailed": "resireg_train.cli.job",
        "RunFolderBusy": "resireg_train.cli.job",
        "RunFolderLock": "resireg_train.cli.job",
        "SweepRecords": "resireg_train.cli.job",
        "added_keys": "resireg_train.cli.job",
        "hydra_entry_point": "resireg_train.cli.job",
        "instantiate_group": "resireg_train.cli.job",
        "hold_run_folder": "resireg_train.cli.job",
        "optimized_value": "resireg_train.cli.job",
        "process_rank": "resireg_train.cli.job",
        "register_resolvers": "resireg_train.cli.job",
        "run_task": "resireg_train.cli.job",
        "safe_dirname": "resireg_train.cli.job",
        "top_level_keys": "resireg_train.cli.job",
    },
)
