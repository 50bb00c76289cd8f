"""`python -m kneeseat_core` runs the kneeseat CLI."""
import sys

from .cli.main import main

sys.exit(main())
