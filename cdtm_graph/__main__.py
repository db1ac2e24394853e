import sys

from cdtm_graph.cli import main

sys.exit(main())
