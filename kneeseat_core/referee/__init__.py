"""The referee: an independent judge of "at rest" that shares no code with the settle.

`judge` climbs the travel from a pose with its own python-fcl objects, boolean queries and
scipy's Nelder-Mead; `cells` judges the cells a table claims at rest, each from the
table's own record of its problem. Nothing here imports `kneeseat_core.settle`
(test/test_layers.py pins it).
"""
from .cells import body_load, CellVerdict, changed_cells, mesh_file, sample_cells, verify_table
from .judge import Envelope, Referee, Verdict

__all__ = ['Envelope', 'Verdict', 'Referee', 'CellVerdict', 'sample_cells', 'changed_cells',
           'verify_table', 'mesh_file', 'body_load']
