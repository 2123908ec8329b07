import sys

from softcrawl.cli import main

sys.exit(main())
