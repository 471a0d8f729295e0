"""Navigation filters sharing one interface (see :mod:`opnav.filters.base`)."""
