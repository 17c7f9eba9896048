"""Studies: many scenes, samples, injections or fits from one file, run on Dask.

    clumpylen study STUDY.toml --out DIR [--scheduler ADDRESS] [--workers N]

`spec` (the study file), `tasks` (what to run, with per-task seeds), `work` (one task
on a worker), `runner` (Dask), `store` (per-task files, gathered tables, zarr), `plots`.
"""

from .runner import run_study
from .spec import KINDS, Study, load_study, study_from_dict

__all__ = ["KINDS", "Study", "load_study", "run_study", "study_from_dict"]
