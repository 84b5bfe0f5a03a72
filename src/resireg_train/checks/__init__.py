"""The checks of whole commands (train, eval, map, resume): above the packages whose tables they read."""
