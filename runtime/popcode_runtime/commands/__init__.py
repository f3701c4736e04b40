"""The ``popcode`` command line: predict, info, bench and ``popcode run``, and the pictures of ``--draw``."""
