"""``dermis profile`` checks its options before any work (optics/profile_command.py).

An option outside the bounds the scene schema uses (``--mc`` as ``[optics] photons``,
``--seed`` as ``[optics] seed``, ``--poles`` up to the adaptive count's cap), or a stack whose
estimated peak memory exceeds the machine's, exits with code 2 and one message naming the
option, its value and what is allowed: no traceback, nothing computed.  ``--poles 100000000``
used to reach 20 GB before the kernel killed it without a word, and ``--mc 3000000000`` ran
although scenes cap photons at 2e9.
"""
import os
import resource
import subprocess
import sys

import pytest

from dermis.optics.layers import MAX_MC_PHOTONS, PRESETS
from dermis.optics.multipole import MAX_POLES


def dermis_profile(*argv, memory_mb=None, timeout=120):
    """``dermis profile ARGV`` in a child process with at most 4 GiB of address space (a
    command that allocates before checking fails there instead of exhausting the machine)."""
    env = dict(os.environ)
    env.pop("DERMIS_MEMORY_MB", None)
    if memory_mb is not None:
        env["DERMIS_MEMORY_MB"] = str(memory_mb)

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))

    return subprocess.run([sys.executable, "-m", "dermis.pipeline.cli", "profile", *map(str, argv)],
                          capture_output=True, text=True, timeout=timeout, env=env,
                          preexec_fn=limit)


def refused(res, *needles):
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    assert "Traceback" not in res.stderr and res.stdout == "", res.stderr[-2000:]
    for needle in needles:
        assert needle in res.stderr, (needle, res.stderr)


@pytest.mark.parametrize("poles", [100_000_000, MAX_POLES + 1, -1])
def test_poles_outside_the_cap_exit_2_naming_the_option(poles):
    refused(dermis_profile("two_layer", "--poles", poles),
            f"--poles = {poles}: must be an integer in 0 .. {MAX_POLES}")


def test_poles_at_the_cap_run():
    res = dermis_profile("skin1", "--poles", MAX_POLES)
    assert res.returncode == 0 and len(res.stdout.splitlines()) == 3, res.stderr[-2000:]
    refused(dermis_profile("skin1", "--poles", MAX_POLES + 1), f"--poles = {MAX_POLES + 1}")


@pytest.mark.parametrize("photons", [3_000_000_000, MAX_MC_PHOTONS + 1, -5])
def test_mc_outside_the_scene_bound_exit_2_naming_the_option(photons):
    refused(dermis_profile("skin1", "--mc", photons, timeout=60),
            f"--mc = {photons}: must be a photon count per channel in 1 .. {MAX_MC_PHOTONS}")


@pytest.mark.parametrize("seed", [-1, 2**32 - 1])
def test_seed_outside_its_bound_exit_2_naming_the_option(seed):
    refused(dermis_profile("skin1", "--mc", 1000, "--seed", seed, timeout=60),
            f"--seed = {seed}: must be an integer in 0 .. {2**32 - 2}")


def test_every_bad_option_is_named_at_once():
    refused(dermis_profile("skin1", "--poles", -3, "--mc", -5, "--models", "mc"),
            "--poles = -3", "--mc = -5", "--models: mc: unknown")


def test_memory_estimate_beyond_the_machine_exit_2():
    # two_layer needs about 0.7 GiB at its peak (532 MiB measured); with 100 MiB it is refused
    refused(dermis_profile("two_layer", memory_mb=100),
            "profile two_layer: needs about", "this machine has 0.10 GiB ($DERMIS_MEMORY_MB")


def test_memory_estimate_grows_with_the_poles():
    from dermis.optics.profile_command import estimate_memory
    total = {p: sum(b for _, b in estimate_memory(PRESETS["two_layer"], p))
             for p in (None, MAX_POLES, 100_000_000)}
    # measured peaks: 532 MiB (adaptive), 694 MiB (--poles 2000); 1e8 pole pairs: > 20 GB
    assert 532 << 20 <= total[None] < total[MAX_POLES] < 1 << 30
    assert total[100_000_000] > 100 << 30
