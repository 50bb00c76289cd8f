"""From a knee config to a table: every grid cell settled in warm-started chains.

`phases` orders the sweep (centre cells, spines along flexion, ribs along varus), `chains`
settles one chain of cells in a worker, `scene` rebuilds the rigid bodies once per worker,
`executors` says where chains run, `continuity` measures the neighbour steps of the result
and `build` packages it as a table. `cluster` (Dask) is imported only by
`executor_for` when a scheduler is given, never here: it costs seconds of start-up.
"""
from .build import backed_out_lines, build_table, make_table, queries_per_cell, summary_line
from .chains import (ChainJob, ChainResult, cold_start, mean_change, prepare_worker,
                     rest_change, run_chain, SoftTissue, warm_start)
from .continuity import continuity, neighbour_steps
from .executors import executor_for, InlineExecutor, process_executor
from .phases import ribs_beside, sweep, SweepResult
from .scene import scene_bodies, SceneSpec

__all__ = ['sweep', 'SweepResult', 'ChainJob', 'ChainResult', 'SoftTissue', 'run_chain',
           'prepare_worker',
           'warm_start', 'cold_start', 'rest_change', 'mean_change', 'ribs_beside',
           'SceneSpec', 'scene_bodies', 'InlineExecutor', 'process_executor', 'executor_for',
           'continuity', 'neighbour_steps', 'make_table', 'build_table', 'summary_line',
           'queries_per_cell', 'backed_out_lines']
