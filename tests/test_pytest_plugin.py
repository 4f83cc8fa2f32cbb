"""The pytest plugin users get with the package: a device fixture that is the virtual
device by default and a real port when one is given."""
from imubench.device.sim import VirtualBench

USER_TEST = """
def test_device(imubench_device):
    info = imubench_device.info()
    assert info.sensors_present == 0b1111
    imubench_device.start_stream(500)
    assert len(imubench_device.read(n_samples=100)) == 100
    imubench_device.stop_stream()
"""


def test_fixture_starts_the_virtual_device_by_default(pytester, monkeypatch):
    monkeypatch.delenv("IMUBENCH_PORT", raising=False)
    pytester.makepyfile(USER_TEST)
    pytester.runpytest_subprocess("-p", "no:cacheprovider").assert_outcomes(passed=1)


def test_fixture_uses_the_given_port(pytester, monkeypatch):
    monkeypatch.delenv("IMUBENCH_PORT", raising=False)
    with VirtualBench(speed=0, seed=9) as vb:
        USER_PORT = vb.port_url
        pytester.makepyfile(USER_TEST + f"""
def test_it_is_the_given_device(imubench_port):
    assert imubench_port == "{USER_PORT}"
""")
        r = pytester.runpytest_subprocess("-p", "no:cacheprovider", f"--imubench-port={USER_PORT}")
    r.assert_outcomes(passed=2)
