import sys

from jaxplush.cli import main

sys.exit(main())
