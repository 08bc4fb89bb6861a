"""``python -m hybridcomp``: the ``hybridcomp`` command."""

import sys

from hybridcomp.cli import main

sys.exit(main())
