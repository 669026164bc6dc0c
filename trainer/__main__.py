"""`python -m trainer ...`: trainer/cli.py."""
import sys

from .cli import main

sys.exit(main())
