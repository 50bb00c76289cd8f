"""`python -m kneeseat_core` runs the kneeseat CLI."""
from .console import run

run()
