"""``python -m fem3d``: the same as the ``fem3d`` script."""

import sys

from fem3d.app.cli import main

sys.exit(main())
