"""The ``relpoint`` command line: thin click commands over library calls in ``relpoint`` and ``formats``."""
