from bubsub.clients.cli.main import main

__all__ = ["main"]
