"""``python -m bubsub.service``: same as ``bubsub serve``."""

import sys

from .cli import main

sys.exit(main())
