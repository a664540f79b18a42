"""iniVation USB cameras (DVXplorer, DAVIS) through pyusb, without libcaer.

`protocol.py` holds the wire facts, `words.py` decodes the bulk stream, `encode.py` writes one (for the
fake device and tests), `fake.py` is a device behind pyusb's backend interface, `driver.py` opens and
streams a camera and `source.py` plays one as an event source of the camera service.
"""
