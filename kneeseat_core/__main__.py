"""`python -m kneeseat_core` runs the kneeseat CLI."""
from .cli.main import run

run()
