"""Thin CLI modules for ``detector``: one file per subcommand (parse arguments, call the library, print)."""
