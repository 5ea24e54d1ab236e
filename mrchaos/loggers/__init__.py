"""Loggers: the rerun logger (a TorchRL logger) and the bench's episode recorder."""
