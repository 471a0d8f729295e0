"""Sub-commands of the ``opnav`` CLI, one module each (see :mod:`opnav.cli`)."""
