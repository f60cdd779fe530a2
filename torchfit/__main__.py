"""Hydra entry point: ``python -m torchfit experiment=tshape``.

``@hydra.main`` lives here so that ``configs/`` resolves next to this file, whether torchfit
runs from a checkout or from an installed package.
"""

from __future__ import annotations

import logging
import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from .run import run  # also registers the ${torchfit_data:...} resolver


@hydra.main(version_base="1.3", config_path="configs", config_name="config")
def main(cfg: DictConfig) -> None:
    logging.getLogger("torchfit").setLevel(logging.WARNING if cfg.quiet else logging.INFO)
    try:
        run(cfg, HydraConfig.get().runtime.output_dir)
    except ValueError as err:  # bad input: one clear line and a non-zero exit, no traceback
        print(f"torchfit: error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
