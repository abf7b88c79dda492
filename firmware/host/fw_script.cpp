// Drives the firmware core from a script on stdin, on a virtual clock, and
// prints every byte it sends: the unit-test harness of tests/test_firmware.py
// (which checks the frames with mrctl's own decoder). One command a line:
//
//   crc TEXT                      print CRC-16/CCITT-FALSE of the ASCII TEXT
//   enc_setpoint SEQ I FLAGS WD   print a SETPOINT frame
//   enc_sample SEQ ECHO T X V F I STATUS    (F may be nan)
//   enc_error VERSION SEQ ECHO CODE DETAIL
//   config load_cell 0|1          rebuild the device (before any other device command)
//   at T_US                       set the device clock (µs)
//   adc X_COUNTS F_COUNTS         the readings of the following ticks
//   fault 0|1                     the driver's fault line
//   estop 0|1                     the E-stop input (1 = open), live: the next tick or output change reads it
//   monitor A|nan                 the driver's current monitor
//   tick                          a sampling tick at the current time
//   poll                          the watchdog check at the current time
//   rx HEX                        bytes from the host (no spaces)
//   state                         print "state applied_A enabled tripped out_counts out_enable estop"
//
// Output: "tx HEX" per frame sent, "hex HEX" / "crc 0xXXXX" for the encoders.
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <new>
#include <string>

#include "board_config.h"
#include "mrctl_device.h"

namespace {

void print_hex(const char* tag, const uint8_t* p, size_t n) {
  printf("%s ", tag);
  for (size_t i = 0; i < n; ++i) printf("%02x", p[i]);
  printf("\n");
}

class ScriptIo : public mrctl_fw::DeviceIo {
 public:
  uint32_t counts = 0;
  bool enable = false;
  bool estop = false;
  void send(const uint8_t* data, size_t n) override { print_hex("tx", data, n); }
  void set_output(uint32_t c, bool e) override {
    counts = c;
    enable = e;
  }
  bool estop_open() override { return estop; }
};

size_t from_hex(const char* s, uint8_t* out, size_t cap) {
  size_t n = 0;
  while (s[0] && s[1] && n < cap) {
    char byte[3] = {s[0], s[1], 0};
    out[n++] = static_cast<uint8_t>(strtoul(byte, nullptr, 16));
    s += 2;
  }
  return n;
}

}  // namespace

int main() {
  ScriptIo io;
  mrctl_fw::DeviceConfig cfg = board::kDeviceConfig;
  alignas(mrctl_fw::Device) static unsigned char storage[sizeof(mrctl_fw::Device)];
  mrctl_fw::Device* dev = new (storage) mrctl_fw::Device(cfg, io);
  mrctl_fw::RawInputs raw = {2048, 2048, false, NAN};
  uint32_t now = 0;
  char line[4096];
  while (fgets(line, sizeof line, stdin)) {
    char cmd[32] = {0};
    if (sscanf(line, "%31s", cmd) != 1) continue;
    const char* rest = line + strlen(cmd);
    while (*rest == ' ') ++rest;
    const std::string c = cmd;
    if (c == "crc") {
      std::string text = rest;
      while (!text.empty() && (text.back() == '\n' || text.back() == '\r')) text.pop_back();
      printf("crc 0x%04X\n", mrctl_fw::crc16_ccitt_false(reinterpret_cast<const uint8_t*>(text.data()), text.size()));
    } else if (c == "enc_setpoint") {
      unsigned long seq, flags, wd;
      float I;
      if (sscanf(rest, "%lu %f %lu %lu", &seq, &I, &flags, &wd) != 4) return 2;
      uint8_t out[mrctl_fw::kSetpointFrame];
      const mrctl_fw::SetpointFields f = {static_cast<uint32_t>(seq), I, static_cast<uint8_t>(flags),
                                          static_cast<uint8_t>(wd)};
      print_hex("hex", out, mrctl_fw::encode_setpoint(out, f));
    } else if (c == "enc_sample") {
      unsigned long seq, echo, t, status;
      float x, v, F, I;
      if (sscanf(rest, "%lu %lu %lu %f %f %f %f %lu", &seq, &echo, &t, &x, &v, &F, &I, &status) != 8) return 2;
      uint8_t out[mrctl_fw::kSampleFrame];
      const mrctl_fw::SampleFields f = {static_cast<uint32_t>(seq), static_cast<uint32_t>(echo),
                                        static_cast<uint32_t>(t), x, v, F, I, static_cast<uint16_t>(status)};
      print_hex("hex", out, mrctl_fw::encode_sample(out, f));
    } else if (c == "enc_error") {
      unsigned long ver, seq, echo, code, detail;
      if (sscanf(rest, "%lu %lu %lu %lu %lu", &ver, &seq, &echo, &code, &detail) != 5) return 2;
      uint8_t out[mrctl_fw::kErrorFrame];
      print_hex("hex", out, mrctl_fw::encode_error(out, static_cast<uint32_t>(seq), static_cast<uint32_t>(echo),
                                                   static_cast<uint8_t>(code), static_cast<uint8_t>(detail),
                                                   static_cast<uint8_t>(ver)));
    } else if (c == "config") {
      int on = 1;
      if (sscanf(rest, "load_cell %d", &on) != 1) return 2;
      cfg.has_load_cell = on != 0;
      dev->~Device();
      dev = new (storage) mrctl_fw::Device(cfg, io);
    } else if (c == "at") {
      now = static_cast<uint32_t>(strtoul(rest, nullptr, 10));
    } else if (c == "adc") {
      long x, f;
      if (sscanf(rest, "%ld %ld", &x, &f) != 2) return 2;
      raw.x_counts = static_cast<int32_t>(x);
      raw.force_counts = static_cast<int32_t>(f);
    } else if (c == "fault") {
      raw.driver_fault = atoi(rest) != 0;
    } else if (c == "estop") {
      io.estop = atoi(rest) != 0;
    } else if (c == "monitor") {
      raw.current_monitor_A = strtof(rest, nullptr);
    } else if (c == "tick") {
      dev->tick(raw, now);
    } else if (c == "poll") {
      dev->poll(now);
    } else if (c == "rx") {
      uint8_t bytes[2048];
      const size_t n = from_hex(rest, bytes, sizeof bytes);
      dev->receive(bytes, n, now);
    } else if (c == "state") {
      printf("state %.9g %d %d %u %d %d\n", static_cast<double>(dev->applied_A()), dev->output_enabled() ? 1 : 0,
             dev->watchdog_tripped() ? 1 : 0, io.counts, io.enable ? 1 : 0, dev->estop_latched() ? 1 : 0);
    } else {
      fprintf(stderr, "fw_script: unknown command %s\n", cmd);
      return 2;
    }
    fflush(stdout);
  }
  return 0;
}
