"""Data files shipped with sysid, found with :mod:`importlib.resources` (installed or in a checkout).

- ``default.yaml``: system-identification defaults (the ``bag`` topic roles read by
  :func:`sysid.bagio.reader.load_bag_config`, the ``noise`` estimation read by
  :func:`sysid.noise.noise_config`).
- ``feats_indentation.yaml``: the FEATS indentation data set of ``thinshell indent``
  (:func:`sysid.indentation_fit.load_indentation_config`).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from sim_core.errors import ConfigError

DEFAULT_CONFIG = "default.yaml"
FEATS_INDENTATION = "feats_indentation.yaml"


def data_file(name: str) -> Path:
    """The path of the packaged data file ``name`` (sysid is installed unzipped, so it is a file).

    Raises:
        ConfigError: no such file in the package (the message lists the packaged ones).
    """
    root = resources.files(__name__)
    path = Path(str(root.joinpath(name)))
    if not path.is_file():
        known = sorted(p.name for p in root.iterdir() if p.name.endswith(".yaml"))
        raise ConfigError(f"sysid data file {name!r} is not in the package {__name__} ({root}); packaged: {known}")
    return path
