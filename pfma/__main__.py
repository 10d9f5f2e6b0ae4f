import sys

from pfma.cli import main

sys.exit(main())
