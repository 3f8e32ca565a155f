"""A Dask LocalCluster for tests/runtime/test_cluster.py, hosted in a process of its own so the
test process never runs Dask's threads (runtime/parallel forks only without foreign threads).

Prints the scheduler's address, then answers commands on stdin, one line each:
``kill-busy``: SIGKILL a worker process while it runs one of rotonly's tasks (prints which);
``workers``: waits until both workers are up again (prints their number). EOF closes the cluster.
"""

from __future__ import annotations

import os
import signal
import sys
import time


def main() -> None:
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                           host="127.0.0.1")
    client = Client(cluster)
    print(cluster.scheduler_address, flush=True)
    for line in sys.stdin:
        command = line.strip()
        if command == "kill-busy":
            pids = client.run(os.getpid)
            deadline = time.monotonic() + 300
            answer = "nothing to kill"
            while time.monotonic() < deadline:
                busy = {worker: [str(key) for key in keys] for worker, keys in client.processing().items()
                        if any(str(key).startswith("rotonly-") for key in keys)}
                if busy:
                    worker, keys = next(iter(busy.items()))
                    os.kill(pids[worker], signal.SIGKILL)
                    answer = f"killed {worker} running {' '.join(sorted(keys))}"
                    break
                time.sleep(0.005)
            print(answer, flush=True)
        elif command == "workers":
            client.wait_for_workers(2, timeout=120)
            print(len(client.scheduler_info()["workers"]), flush=True)
    client.close()
    cluster.close()


if __name__ == "__main__":
    main()
