import sys

from rtv3_maniskill.cli import main

sys.exit(main())
