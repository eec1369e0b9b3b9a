"""The cars' protocol (docs/guide/cooperation.md): what a car sends (``message``), what lies between the cars
(``late_fusion.Channel``: pose error, ``pose_noise``; late messages moved to now by each sender's own tracks,
``senders``), and how a receiving car pools what it gets (``late_fusion``: the best car, ``agreement``,
``calibration``). Everything here reads detections: the models run in ``pnyolo.engine.predict``."""
