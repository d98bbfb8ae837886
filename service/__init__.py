"""The REST service: a thin shell around :mod:`recovery`."""
