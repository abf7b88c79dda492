// Teensy 4.x board: pins and calibration, as data (no Arduino headers, so the
// host build in firmware/host/ runs the same numbers). Wiring: firmware/README.md.
// Change these for your sensors; every figure is the sensor's data sheet and
// your signal conditioning, not a property of mrctl.
#pragma once

#include <stdint.h>

#include "mrctl_device.h"

namespace board {

// pins (Teensy 4.0 / 4.1)
constexpr uint8_t kPinLvdt = 14;          // A0: LVDT conditioner output, 0.15-3.15 V
constexpr uint8_t kPinLoadCell = 15;      // A1: load-cell amplifier output, 0.15-3.15 V
constexpr uint8_t kPinCurrentMon = 16;    // A2: driver current monitor (optional), 0-3.3 V
constexpr uint8_t kPinDriverPwm = 2;      // PWM -> 2-pole RC -> x1.515 op-amp -> driver 0-5 V input
constexpr uint8_t kPinDriverEnable = 3;   // driver enable input, active high
constexpr uint8_t kPinDriverFault = 4;    // driver fault output, active low (pull-up)
// E-stop / interlock: a normally-closed contact of the E-stop chain between this pin and GND,
// with the pin's pull-up: closed (running) reads LOW, open (stop pressed, wire broken) reads HIGH
constexpr uint8_t kPinEstop = 5;
constexpr bool kEstopOpenHigh = true;     // the level that means "open": HIGH with the wiring above
constexpr uint8_t kPinHeartbeat = 13;     // LED: toggles every 500 ticks

constexpr bool kHasCurrentMonitor = false;  // true once A2 is wired to the driver's monitor
constexpr float kCurrentMonitorAPerCount = 2.0f / 4095.0f;  // 0-3.3 V = 0-2 A (example)

constexpr uint32_t kSampleRateHz = 1000;  // the hardware timer's rate
constexpr int kAdcBits = 12;              // 0..4095 over 0..3.3 V
constexpr int kAdcAveraging = 4;          // hardware averaging per reading
constexpr int kPwmBits = 12;              // 0..4095
constexpr float kPwmFrequencyHz = 36621.09f;  // the ideal 12-bit PWM frequency at 600 MHz

// ADC: 4095 counts over 3.3 V. Both sensors are scaled to 0.15-3.15 V (3 V
// span, mid-scale 1.65 V = 2048 counts); readings within 16 counts of a rail
// mean a saturated or disconnected sensor (SENSOR_FAULT).
constexpr float kCountsPerV = 4095.0f / 3.3f;
constexpr float kLvdtMPerV = 0.050f / 3.0f;    // ±25 mm stroke over 3 V
constexpr float kLoadCellNPerV = 4000.0f / 3.0f;  // ±2 kN over 3 V

// driver: 0-5 V in -> 0-2 A out (LORD Wonder Box kind); PWM full scale is 5 V
// after the op-amp, so 4095 counts = 2 A
constexpr float kDriverAPerFullScale = 2.0f;

constexpr mrctl_fw::DeviceConfig kDeviceConfig = {
    /* x */ {2048, kLvdtMPerV / kCountsPerV, 16, 4079},
    /* force */ {2048, kLoadCellNPerV / kCountsPerV, 16, 4079},
    /* has_load_cell */ true,
    /* sample_period_s */ 1.0f / kSampleRateHz,
    /* velocity_cutoff_hz */ 50.0f,
    /* I_max_A */ 2.0f,
    /* output_counts_per_A */ 4095.0f / kDriverAPerFullScale,
    /* output_max_counts */ 4095,
};

}  // namespace board
