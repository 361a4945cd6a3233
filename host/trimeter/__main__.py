import sys

from trimeter.cli import main

sys.exit(main())
