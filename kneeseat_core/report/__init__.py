"""What people look at of a table: curves and maps (`plots`), renders of the bones
(`render`), the secondary motions in Grood-Suntay axes (`kinematics`) and their CSV,
Markdown and figure (`kinematics_report`), the ligaments' strains and forces (`strains`).
Headless matplotlib, atomic PNG writes."""
from .kinematics import (DEFAULT_ANGLES_DEG, knee_kinematics, KneeKinematics, Landmarks,
                         landmarks, table_landmarks)
from .kinematics_report import (kinematics_markdown, plot_kinematics, read_reference,
                                write_kinematics_csv)
from .plots import plot_convergence_map, plot_session, plot_table
from .render import render_table
from .strains import bundle_loads, BundleLoads, plot_bundle_strains, write_bundle_csv

__all__ = ['plot_table', 'plot_convergence_map', 'plot_session', 'render_table',
           'knee_kinematics', 'KneeKinematics', 'Landmarks', 'landmarks', 'table_landmarks',
           'DEFAULT_ANGLES_DEG',
           'kinematics_markdown', 'plot_kinematics', 'read_reference', 'write_kinematics_csv',
           'BundleLoads', 'bundle_loads', 'write_bundle_csv', 'plot_bundle_strains']
