"""narxwatch's service: the REST API, the jobs, the dashboard and the ``narxwatch`` command line."""
