"""`python -m learnest.service.cli`: the same as the `learnest` command."""
import sys

from .run import main

sys.exit(main())
