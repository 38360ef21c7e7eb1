import sys

from rockwave.app.cli import main

sys.exit(main())
