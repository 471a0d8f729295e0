"""Sub-commands of the ``opnav`` CLI, one module each (see :mod:`opnav.cli`): they parse arguments
and print; the work is library code they import inside ``add_arguments``/``run`` (their top-level
imports stay light, so ``opnav --help`` does not load the library)."""
