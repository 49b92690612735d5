import sys

from nerfpipe.cli import main

sys.exit(main())
