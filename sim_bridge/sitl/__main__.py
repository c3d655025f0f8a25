import sys

from sim_bridge.sitl.cli import main

sys.exit(main())
