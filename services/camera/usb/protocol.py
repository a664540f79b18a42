"""Wire facts of iniVation's USB cameras (see shared/reference/inivation_usb_protocol.md, sections 1-4, 11).

Only numbers live here: ids, requests, module and parameter addresses, the models the driver knows.
"""

from __future__ import annotations

from dataclasses import dataclass

VID = 0x152A
PID_DVXPLORER, PID_DAVIS_FX3, PID_DAVIS_FX2 = 0x8419, 0x841A, 0x841B
PIDS = (PID_DVXPLORER, PID_DAVIS_FX3, PID_DAVIS_FX2)
BCD_MINI = 4  # bcdDevice high byte of the DVXplorer Mini (CX3 bridge, 32-bit words): not supported yet

VR_FPGA_CONFIG, VR_FPGA_CONFIG_MULTIPLE = 0xBF, 0xC2
REQ_OUT, REQ_IN = 0x40, 0xC0  # vendor, device
EP_DATA, EP_DEBUG = 0x82, 0x81
TIMEOUT_MS = 1000

# modules
MUX, DVS, APS, IMU, EXTINPUT, BIAS, SYSINFO, USB = 0, 1, 2, 3, 4, 5, 6, 9
# MUX params
MUX_RUN, MUX_TS_RUN, MUX_TS_RESET, MUX_RUN_CHIP, MUX_DROP_EXT, MUX_DROP_DVS = 0, 1, 2, 3, 4, 5
MUX_STAT_DVS_DROPPED = 83  # 64-bit: 83 upper, 84 lower
# SYSINFO params
LOGIC_VERSION, CHIP_ID, IS_MASTER, LOGIC_CLOCK, ADC_CLOCK, USB_CLOCK, CLOCK_DEVIATION, LOGIC_PATCH = range(8)
# DVS params
DVS_COLUMNS, DVS_ROWS, DVS_ORIENTATION, DVS_RUN = 0, 1, 2, 3
DVS_ROI = (41, 42, 43, 44)  # DAVIS: start column, start row, end column, end row (inclusive)
# IMU params
IMU_TYPE, IMU_ORIENTATION, IMU_RUN_ACCEL, IMU_RUN_GYRO, IMU_RUN_TEMP = 0, 1, 2, 3, 4
USB_RUN, USB_EARLY_PACKET_DELAY = 0, 1

LOGIC_REQUIRED = 18
# DVXplorer sensor registers (module 5, 16-bit wIndex)
DVX_MODE = 0x3000  # 0 off, 1 monitor, 2 stream
DVX_TS_RESET = 0x3238
DVX_DTAG = 0x3201  # 0 stop, 1 start, 2 restart
DVX_CROP_BYPASS = 0x3300
DVX_CROP_Y = (0x3301, 0x3302, 0x3303, 0x3304)  # start group, start mask, end group, end mask
DVX_CROP_X = (0x3305, 0x3306, 0x3307, 0x3308)  # start hi, lo, end hi, lo
DVX_MODE_STREAM = 2

# DVXplorer bias presets (section 7.2): REG[0x000B], REG[0x0012], ON REG[0x001C], OFF REG[0x001E]
DVX_BIAS_PRESETS = {"very_low": (0x06, 0x7D, 0x06, 0x02), "low": (0x06, 0x7D, 0x03, 0x05),
                    "default": (0x06, 0x7D, 0x00, 0x08), "high": (0x04, 0x7F, 0x05, 0x03),
                    "very_high": (0x04, 0x7F, 0x02, 0x06)}
# DAVIS346 libcaer default biases (section 7.1), module 5 param -> 16-bit code
DAVIS346_BIASES = {0: 0x019B, 1: 0x0195, 2: 0x01E0, 3: 0x01C1, 4: 0x01D5, 8: 0x5A4F, 9: 0x7D7E, 10: 0x427F,
                   11: 0x5FFF, 12: 0x401F, 13: 0x690F, 14: 0x23AD, 15: 0x110D, 16: 0x419D, 17: 0x614D,
                   18: 0x6DBF, 19: 0x514D, 20: 0x001F, 21: 0x63CD, 22: 0x531F, 23: 0x65BF, 24: 0x450D,
                   25: 0x798D, 26: 0x5FFF, 27: 0x5FFF, 34: 0x5FEF, 35: 0x8410, 36: 0x8410}
DAVIS240_BIASES = {0: 0x427F, 1: 0x5FFF, 2: 0x400F, 3: 0x5B9B, 4: 0x573B, 5: 0x6DBF, 6: 0x5A4F, 7: 0x690F,
                   8: 0x23AD, 9: 0x110D, 10: 0x419D, 11: 0x65BF, 12: 0x531F, 13: 0x450D, 14: 0x798D,
                   15: 0x5FFF, 16: 0x5FFF, 17: 0x7D7F, 18: 0x6FDF, 19: 0x5FEF, 20: 0x8410, 21: 0x8410}
# DAVIS bias sensitivity presets: ONBN (11) and OFFBN (12) codes moved away from (or towards) DIFFBN
DAVIS_SENSITIVITY = {"low": (0x5FFF, 0x400F), "default": (0x5FFF, 0x401F), "high": (0x5A4F, 0x427F)}

# DAVIS chip ids (SYSINFO 1) -> model; DVXplorer: 20 full, 19 Lite
DAVIS_CHIPS = {0: "DAVIS240A", 1: "DAVIS240B", 2: "DAVIS240C", 3: "DAVIS128", 4: "DAVIS346A", 5: "DAVIS346",
               6: "DAVIS640", 7: "DAVIS640H", 8: "DAVIS208", 9: "DAVIS346BSI"}
DVX_CHIPS = {20: "DVXplorer", 19: "DVXplorer Lite"}


@dataclass(frozen=True)
class Family:
    """What a PID tells: the stream's layout and the firmware it needs."""

    name: str
    dvx: bool  # column + 8-pixel-group words (DVXplorer), else row/column words (DAVIS)
    min_firmware: int


FAMILIES = {PID_DVXPLORER: Family("DVXplorer", True, 8), PID_DAVIS_FX3: Family("DAVIS FX3", False, 6),
            PID_DAVIS_FX2: Family("DAVIS FX2", False, 4)}
# the models of `etam usb-decode --model`: word layout and native size
MODELS = {"dvxplorer": (True, 640, 480), "dvxplorer-lite": (True, 320, 240), "davis346": (False, 346, 260),
          "davis240": (False, 240, 180)}
