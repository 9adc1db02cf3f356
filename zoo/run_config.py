"""Safe loading of the ``config.yml`` / ``args.yml`` files rl_zoo3 writes (moved to :mod:`vafn_sb3.common.run_yaml`,
where ``vafn_sb3.loading`` uses it too; re-exported here)."""

from vafn_sb3.common.run_yaml import (  # noqa: F401
    ALLOWED_NAME_MODULES,
    PYTHON_TAG,
    RunConfigLoader,
    load_run_config,
    load_run_yaml,
    resolve_allowed_name,
)
