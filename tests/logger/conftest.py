def pytest_configure(config):
    config.addinivalue_line("markers", "vcan: needs real SocketCAN vcan0 (native, or a VM set up by .ci/vcan-setup)")
