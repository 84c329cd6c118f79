"""Every saved figure says where it was measured: the machine record that reports and benchmarks
share names the CPU and the versions of the libraries that did the arithmetic."""

from __future__ import annotations

import os

import numpy as np
import torch

from sim_harness.experiments.machine import machine


def test_the_record_names_the_cpu_and_the_libraries_in_use() -> None:
    where = machine()
    assert where["cpu"] and where["cpus"] == os.cpu_count()
    assert where["numpy"] == np.__version__ and where["torch"] == torch.__version__


def test_what_a_benchmark_measured_about_the_machine_is_kept_beside_it() -> None:
    where = machine(load_average_1m={"before": 0.5, "after": 1.5})
    assert where["load_average_1m"] == {"before": 0.5, "after": 1.5}
    assert where["cpu"] == machine()["cpu"]
