import sys

from pointfence.cli import main

sys.exit(main())
