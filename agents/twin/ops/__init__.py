"""ops layer (docs/architecture.md): the deployed twin from outside: instances, checks, history, replay."""
