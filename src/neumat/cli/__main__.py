"""`python -m neumat.cli`: the `neumat` command."""
import sys

from neumat.cli import main

sys.exit(main())
