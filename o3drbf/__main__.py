import sys

from o3drbf.cli.commands import main

sys.exit(main())
