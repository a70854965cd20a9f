"""Thin CLI modules for ``mpchair``: one file per subcommand (parse arguments, call the library, print)."""
