"""Training: the loop (``train``), which validates the model it trains by the evaluation's own scoring and pictures,
so it sits above ``evaluation``; ``engine`` (predicting, checkpoints, devices and threads) imports no analysis."""
