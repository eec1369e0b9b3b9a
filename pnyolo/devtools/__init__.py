"""What the developer scripts in benchmarks/ share: measuring this tree beside a git revision (``sides``)."""
