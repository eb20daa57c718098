"""Records shared by the API and the workers: settings, the job database, job kinds and statuses.

Imports neither ``api`` nor ``workers``: both depend on it, never the other way round.
"""
