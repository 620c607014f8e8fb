"""Datasets (SPEC section 8): record rollouts as LeRobot datasets, pack them, list and download them.

Nothing here imports lerobot, torch or huggingface_hub at import time; they are loaded by the
functions that need them.
"""

from mewa_bench.datasets.catalog import (DatasetError, add_to_catalog, dataset_info, default_catalog_path,
                                         load_catalog)
from mewa_bench.datasets.downloader import Downloaded, download
from mewa_bench.datasets.lerobot_recorder import LeRobotSink, load_metadata, task_description
from mewa_bench.datasets.pack import pack_dataset
from mewa_bench.datasets.training_data import (TRAINING_DATASETS, TrainingSpec, build_training_dataset,
                                               check_training_dataset, load_training_dataset, training_spec)
from mewa_bench.datasets.training_keys import TrainingDataError

__all__ = ["DatasetError", "Downloaded", "LeRobotSink", "TRAINING_DATASETS", "TrainingDataError", "TrainingSpec",
           "add_to_catalog", "build_training_dataset", "check_training_dataset", "dataset_info", "default_catalog_path",
           "download", "load_catalog", "load_metadata", "load_training_dataset", "pack_dataset", "task_description",
           "training_spec"]
