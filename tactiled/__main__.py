import sys

from tactiled.cli import main

sys.exit(main())
