// mrctl reference firmware, Teensy 4.0 / 4.1 board file (Teensyduino).
//
// The thin part: a hardware timer (IntervalTimer, a PIT channel) latches the
// two ADC channels at 1 kHz; the main loop hands the latched readings, the USB
// serial bytes and the time to the protocol core (firmware/core/), which does
// everything docs/protocol.md defines, and moves the core's output to the PWM
// and the driver's enable pin. Pins and calibration: board_config.h; wiring
// and flashing: firmware/README.md.
//
// Safety chain on the board: the core applies 0 A on its millisecond watchdog
// (no SETPOINT for watchdog_ms), on a driver fault, on ENABLE clear and while
// the E-stop input is open (latched: ESTOP until a CLEAR_FAULTS once it has
// closed); TeensyIo::set_output writes 0 and the enable LOW whatever it is
// asked while the E-stop pin reads open, so no path drives the output then;
// the timer ISR itself cuts the output at the tick the E-stop input opens, and
// if the main loop stops serving ticks (a hang), after kStallTicks ticks. The
// E-stop chain's hard-wired contacts remove the driver's power whatever this
// board does (docs/hardware.md).
#include <Arduino.h>

#include "board_config.h"
#include "mrctl_device.h"

namespace {

constexpr uint32_t kStallTicks = 5;  // ticks the ISR waits for the main loop

struct Latch {
  int32_t x_counts;
  int32_t force_counts;
  int32_t current_counts;
  bool driver_fault;
  uint32_t t_us;
};

IntervalTimer sample_timer;
volatile Latch latch;
volatile uint32_t ticks_latched = 0;  // written by the ISR
volatile uint32_t ticks_served = 0;   // written by the main loop, read by the ISR

// the E-stop pin, open (stop) or closed (run), with the board's polarity
bool estop_pin_open() { return (digitalReadFast(board::kPinEstop) == HIGH) == board::kEstopOpenHigh; }

class TeensyIo : public mrctl_fw::DeviceIo {
 public:
  void send(const uint8_t* data, size_t n) override {
    // a host that stopped reading must not stall the loop (writes would wait
    // for room): drop the frame instead, as a lost reply
    if (Serial.availableForWrite() < static_cast<int>(n)) {
      ++tx_dropped;
      return;
    }
    Serial.write(data, n);
    Serial.send_now();  // do not wait for the USB buffer to fill: the reply is due now
  }
  uint32_t tx_dropped = 0;
  // 0 and the enable LOW while the E-stop pin reads open, whatever is asked;
  // interrupts off so the timer ISR's cut cannot fall between the read and the writes
  void set_output(uint32_t counts, bool enable) override {
    noInterrupts();
    if (estop_pin_open()) {
      counts = 0;
      enable = false;
    }
    analogWrite(board::kPinDriverPwm, static_cast<int>(counts));
    digitalWriteFast(board::kPinDriverEnable, enable ? HIGH : LOW);
    interrupts();
  }
  bool estop_open() override { return estop_pin_open(); }
};

TeensyIo io;
mrctl_fw::Device device(board::kDeviceConfig, io);

// 1 kHz: take the measurement now; the main loop does the rest
void on_sample_timer() {
  latch.t_us = micros();
  latch.x_counts = analogRead(board::kPinLvdt);
  latch.force_counts = analogRead(board::kPinLoadCell);
  latch.current_counts = board::kHasCurrentMonitor ? analogRead(board::kPinCurrentMon) : -1;
  latch.driver_fault = digitalReadFast(board::kPinDriverFault) == LOW;
  ticks_latched = ticks_latched + 1;
  if (estop_pin_open() || ticks_latched - ticks_served > kStallTicks) {  // E-stop, or the main loop hangs: 0 A here
    analogWrite(board::kPinDriverPwm, 0);
    digitalWriteFast(board::kPinDriverEnable, LOW);
  }
}

}  // namespace

void setup() {
  // 0 A and the driver disabled before anything else (the core drives them from the first tick)
  pinMode(board::kPinDriverEnable, OUTPUT);
  digitalWriteFast(board::kPinDriverEnable, LOW);
  pinMode(board::kPinDriverFault, INPUT_PULLUP);
  pinMode(board::kPinEstop, INPUT_PULLUP);
  pinMode(board::kPinHeartbeat, OUTPUT);
  analogWriteResolution(board::kPwmBits);
  analogWriteFrequency(board::kPinDriverPwm, board::kPwmFrequencyHz);
  analogWrite(board::kPinDriverPwm, 0);
  analogReadResolution(board::kAdcBits);
  analogReadAveraging(board::kAdcAveraging);
  Serial.begin(2000000);  // USB: the baud rate is nominal (docs/protocol.md §9)
  sample_timer.begin(on_sample_timer, 1000000.0f / board::kSampleRateHz);
  sample_timer.priority(64);  // above USB (112), below the most urgent system ISRs
}

void loop() {
  static uint8_t rx[64];
  // a tick latched since the last pass: the core applies a pending SYNC
  // setpoint, checks the watchdog, publishes the sample and answers SYNC requests
  if (ticks_latched != ticks_served) {
    mrctl_fw::RawInputs raw;
    uint32_t t_us;
    noInterrupts();
    raw.x_counts = latch.x_counts;
    raw.force_counts = latch.force_counts;
    raw.driver_fault = latch.driver_fault;
    const int32_t current_counts = latch.current_counts;
    t_us = latch.t_us;
    ticks_served = ticks_latched;  // ticks the loop missed are dropped, never queued
    interrupts();
    raw.current_monitor_A = current_counts >= 0
                                ? static_cast<float>(current_counts) * board::kCurrentMonitorAPerCount
                                : __builtin_nanf("");  // no monitor wired
    device.tick(raw, t_us);
    if (device.counters().ticks % 500 == 0) digitalToggleFast(board::kPinHeartbeat);
  }
  const int avail = Serial.available();
  if (avail > 0) {  // never more than is there: readBytes() then does not wait
    size_t n = static_cast<size_t>(avail) < sizeof rx ? static_cast<size_t>(avail) : sizeof rx;
    n = Serial.readBytes(reinterpret_cast<char*>(rx), n);
    device.receive(rx, n, micros());
  }
  device.poll(micros());
}
