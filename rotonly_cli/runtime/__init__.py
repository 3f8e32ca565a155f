"""How rotonly runs as a process: edge-parallel work in forked processes (``parallel``),
progress bars without a monitor thread (``progress``), the start-up and garbage-collector
costs of the ``rotonly`` process (``startup``)."""
