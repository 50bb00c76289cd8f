"""`python -m kneeseat_core` runs the kneeseat CLI."""
import sys

from .cli import main

sys.exit(main())
