"""Thin CLI modules for ``detector``: one file per subcommand (parse arguments, call the library, print)."""


def config_help(what: str = "Experiment config") -> str:
    """``--config`` help with the packaged configs' names (:func:`detector.config.available_configs`)."""
    from detector.config import available_configs

    return f"{what}: a YAML file's path, or a packaged config's name ({', '.join(available_configs())}); a path wins."


#: The ``--checkpoint`` help's note on packaged weights (:mod:`detector.pretrained`).
PRETRAINED_HELP = "a file, or pretrained:NAME for packaged weights (dense, sparse, sparse_exact)"
