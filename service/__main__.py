"""``python -m bubsub.service``: same as ``bubsub serve``."""

import sys

from bubsub.service.cli import main

sys.exit(main())
