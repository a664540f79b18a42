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

# DVXplorer sensor power-up (section 4.1 A, libcaer 3.3.15): raw register, value
DVX_SENSOR_INIT = ((0x000D, 0x24), (0x000F, 0x07), (0x0010, 0xFF), (0x0013, 0x03), (0x0014, 0x7F), (0x0015, 0x00),
                   (0x3011, 0xA0), (0x3019, 0x00), (0x301E, 0x01), (0x3067, 0x80), (0x3255, 0x0C), (0x3266, 0x08),
                   (0x3235, 0x03), (0x3236, 0xE7), (0x3234, 49), (0x323D, 50), (0x3243, 50), (0x3247, 50),
                   (0x3259, 50), (0x3600, 0x01))
# DVXplorer default readout (section 4.1 B), written while the readout is stopped: trigger mode, global reset
# during readout and fixed read time off, the area-blocking masks, timing (T_ED 2 us, GRS 1 us, the select
# timings, NEXT_SEL 15 with MAX_EVENT_NUM 10, NEXT_GH 4, READ_FIXED 45000) and the activity decision bypassed
DVX_READOUT = ((0x3260, 0), (0x3248, 0), (0x325C, 0),
               *((0x3205 + 2 * i + k, v) for i in range(20) for k, v in ((0, 0x7F), (1, 0xFF))),
               (0x3240, 0), (0x3241, 0), (0x3242, 2), (0x3244, 0), (0x3245, 0), (0x3246, 0), (0x3256, 0),
               (0x3257, 0), (0x3258, 1), (0x323C, 4), (0x324C, 6), (0x324E, 4), (0x324F, 6), (0x3253, 8),
               (0x3254, 10), (0x3261, 0), (0x3262, 15), (0x3251, 10), (0x324B, 4), (0x325D, 0xAF), (0x325E, 0xC8),
               (0x3500, 1), (0x3501, 0x01), (0x3502, 0x2C), (0x3503, 0x00), (0x3504, 0x14), (0x3505, 1),
               (0x3506, 3), (0x3513, 0x01), (0x3514, 0x2C))
# DVXplorer read-modify-write registers (section 4.1 B): register, bits set, bits cleared. Global hold on, global
# reset off; no flatten, ON-only or OFF-only; subsampling and area blocking bypassed (disable bits)
DVX_UPDATES = ((0x3255, 0x01, 0x02), (0x3067, 0x00, 0x70), (0x3200, 0x06, 0x00))
DVX_DUAL_BINNING, DVX_SUBSAMPLE = 0x3202, 0x3204
# IMU defaults (module 3 params): DVXplorer BMI160 800 Hz, +-4 g, +-500 deg/s; DAVIS MPU +-4 g, +-500 deg/s
DVX_IMU = ((5, 6), (6, 2), (7, 1), (8, 5), (9, 2), (10, 2))
DAVIS_IMU = ((5, 0), (6, 1), (7, 1), (10, 1))
# DAVIS chip configuration (module 5 params >= 128, section 4.4 B)
DAVIS_CHIP = ((128, 0), (129, 0), (130, 0), (131, 0), (132, 0), (133, 0), (134, 0), (135, 0), (136, 1), (137, 0),
              (138, 1), (139, 0), (140, 0), (141, 0))
DAVIS_CHIP_346 = ((143, 1), (144, 0))  # DAVIS128/208/346/640 only
# DVS feature flags (module 1, read-only) and the settings each gets when present (section 4.4 B)
DVS_HAS_PIXEL_FILTER, DVS_HAS_BA_FILTER, DVS_HAS_ROI_FILTER, DVS_HAS_SKIP_FILTER, DVS_HAS_POLARITY_FILTER = (
    10, 30, 40, 50, 60)
DVS_BA_FILTER = ((31, 1), (32, 8), (33, 0), (34, 1))  # background activity 2 ms on, refractory off
DVS_SKIP_FILTER = ((51, 0), (52, 5))
DVS_POLARITY_FILTER = ((61, 0), (62, 0), (63, 0))
EXT_HAS_GENERATOR = 10

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
