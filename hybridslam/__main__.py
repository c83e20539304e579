"""``python -m hybridslam`` is the ``hybridslam`` command."""

import sys

from .cli import main

sys.exit(main())
