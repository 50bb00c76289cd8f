"""The `kneeseat` command line (`main`): one module per family of commands."""
from .main import build_parser, main

__all__ = ['main', 'build_parser']
