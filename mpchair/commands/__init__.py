"""Thin CLI modules for ``mpchair``: one file per subcommand (parse arguments, call the library, print)."""

from mpchair.core.config import package_folder, packaged_names


def sensor_help() -> str:
    """``--sensor`` help with the packaged profiles' names (the folder of :data:`mpchair.scan.sensors.SENSOR_DIR`,
    listed without importing the scan stack, which takes a second)."""
    names = ", ".join(packaged_names(package_folder("mpchair", "scan/profiles")))
    return f"Sensor profile: a YAML file's path, or a packaged profile's name ({names}); a path wins."
