"""Prometheus metrics, structured logs and request ids for the service."""

# prometheus-client's variable naming the folder where several processes' metrics are added up.
MULTIPROCESS_DIR = "PROMETHEUS_MULTIPROC_DIR"
