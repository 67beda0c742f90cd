"""Optimization: the parameter owner (``adam``: ``GaussianAdam``), the densification ``Strategy`` interface and the
paper's adaptive density control (``strategy``, ``densify``), the training loss, schedules and the training loop
(``losses``, ``schedules``, ``trainer``)."""
