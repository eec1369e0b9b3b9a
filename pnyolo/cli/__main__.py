"""``python -m pnyolo.cli train|eval|predict ARGS``: what torchrun starts on every rank."""
import sys

from pnyolo.cli.train import main

sys.exit(main())
