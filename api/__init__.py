"""Fotoskhema REST API, tile server and command line."""
