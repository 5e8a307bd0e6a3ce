import sys

from gra_mi.cli.main import main

sys.exit(main())
