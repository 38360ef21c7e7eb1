import sys

from rockwave.cli import main

sys.exit(main())
