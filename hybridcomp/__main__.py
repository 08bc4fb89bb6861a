import sys

from hybridcomp.cli import main

sys.exit(main())
