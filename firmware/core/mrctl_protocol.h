// mrctl serial protocol v1, device side: frame layout, CRC, encoding, and the
// streaming receiver of docs/protocol.md §3.
//
// Portable C++17: no board headers, no dynamic allocation, no exceptions, no
// dependence on the MCU's endianness or alignment (fields are written and read
// byte by byte, floats through memcpy). The host implementation it must agree
// with byte for byte is mrctl/io/protocol/ (tests/test_firmware.py checks it).
#pragma once

#include <stddef.h>
#include <stdint.h>

namespace mrctl_fw {

constexpr uint8_t kPreamble0 = 0xA5;
constexpr uint8_t kPreamble1 = 0x5A;
constexpr uint8_t kVersion = 1;
constexpr size_t kHeaderSize = 9;   // preamble 2, version, type, payload_len, seq u32
constexpr size_t kCrcSize = 2;
constexpr size_t kMaxPayload = 64;  // longest payload any version may declare
constexpr size_t kMaxFrame = kHeaderSize + kMaxPayload + kCrcSize;  // 75

// frame types (bit 7 set = device -> host)
constexpr uint8_t kTypeSetpoint = 0x01;
constexpr uint8_t kTypeChannelQuery = 0x02;
constexpr uint8_t kTypeSample = 0x81;
constexpr uint8_t kTypeChannelList = 0x82;
constexpr uint8_t kTypeSampleX = 0x83;
constexpr uint8_t kTypeError = 0xE1;

constexpr size_t kSetpointPayload = 6;
constexpr size_t kSamplePayload = 26;
constexpr size_t kErrorPayload = 6;
constexpr size_t kSetpointFrame = kHeaderSize + kSetpointPayload + kCrcSize;  // 17
constexpr size_t kSampleFrame = kHeaderSize + kSamplePayload + kCrcSize;      // 37
constexpr size_t kErrorFrame = kHeaderSize + kErrorPayload + kCrcSize;        // 17

// SETPOINT flags
constexpr uint8_t kFlagEnable = 0x01;
constexpr uint8_t kFlagClearFaults = 0x02;
constexpr uint8_t kFlagSync = 0x04;
constexpr uint8_t kFlagChannels = 0x08;

// status bits (same positions as mrctl.io.base.Status)
constexpr uint16_t kStatusDriverFault = 1u << 0;
constexpr uint16_t kStatusSensorFault = 1u << 1;
constexpr uint16_t kStatusWatchdogTripped = 1u << 2;
constexpr uint16_t kStatusOutputEnabled = 1u << 3;
constexpr uint16_t kStatusCurrentClamped = 1u << 4;
constexpr uint16_t kStatusNoLoadCell = 1u << 5;
constexpr uint16_t kStatusRxError = 1u << 6;
constexpr uint16_t kStatusEstop = 1u << 7;

// ERROR codes
constexpr uint8_t kErrBadCrc = 0x01;
constexpr uint8_t kErrBadVersion = 0x02;
constexpr uint8_t kErrUnknownType = 0x03;
constexpr uint8_t kErrBadLength = 0x04;
constexpr uint8_t kErrInternal = 0xFF;

constexpr uint8_t kDefaultWatchdogMs = 50;  // watchdog_ms == 0 on the wire

// CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0.
uint16_t crc16_ccitt_false(const uint8_t* p, size_t n);

// little-endian field access, independent of the CPU's byte order
uint32_t get_u32(const uint8_t* p);
float get_f32(const uint8_t* p);
void put_u16(uint8_t* p, uint16_t v);
void put_u32(uint8_t* p, uint32_t v);
void put_f32(uint8_t* p, float v);

struct SetpointFields {
  uint32_t seq;
  float current_A;
  uint8_t flags;
  uint8_t watchdog_ms;
};

struct SampleFields {
  uint32_t seq;       // device seq: number of the measurement
  uint32_t echo_seq;  // seq of the SETPOINT this answers
  uint32_t t_dev_us;  // device time of the measurement, µs (wraps)
  float x_m;
  float v_mps;
  float F_N;          // NaN without a load cell
  float current_A;    // current applied at the measurement, A
  uint16_t status;
};

// Encoders write a whole frame (header, payload, CRC) into out and return its
// size; out must hold the frame (sizes above). 0 = did not fit.
size_t encode_setpoint(uint8_t* out, const SetpointFields& f);  // host side; tests and tools
size_t encode_sample(uint8_t* out, const SampleFields& f);
size_t encode_error(uint8_t* out, uint32_t seq, uint32_t echo_seq, uint8_t code, uint8_t detail,
                    uint8_t version = kVersion);
// CHANNEL_LIST: echo_seq and comma-separated ASCII names ("" = no channels)
size_t encode_channel_list(uint8_t* out, size_t cap, uint32_t seq, uint32_t echo_seq, const char* names);

// SETPOINT fields of a complete, CRC-checked SETPOINT frame (17 bytes).
SetpointFields decode_setpoint(const uint8_t* frame);

// Receives the Receiver's verdicts. `frame` points into the receiver's buffer
// and is valid only during the call.
class FrameSink {
 public:
  // a CRC-valid frame of any version and type (len = 11 + payload_len)
  virtual void on_frame(const uint8_t* frame, size_t len) = 0;
  // a candidate with a plausible SETPOINT header (A5 5A 01 01 06) failed its CRC
  virtual void on_setpoint_crc_error() = 0;
  // bytes were dropped (noise, a bad header, a failed CRC): RX_ERROR
  virtual void on_discard() = 0;

 protected:
  ~FrameSink() = default;
};

// The streaming receiver of docs/protocol.md §3: bytes in any chunks, noise
// in between; whole CRC-valid frames out. Never blocks, never fails: the worst
// outcome of garbage is a missed frame. Holds at most one candidate frame.
class Receiver {
 public:
  explicit Receiver(FrameSink& sink) : sink_(sink) {}
  void push(uint8_t byte);
  void push(const uint8_t* data, size_t n) {
    for (size_t i = 0; i < n; ++i) push(data[i]);
  }
  void reset() { discard(len_); }

  uint32_t frames = 0;           // valid frames delivered
  uint32_t crc_errors = 0;       // plausible headers that failed the CRC
  uint32_t header_errors = 0;    // preambles followed by an impossible header
  uint32_t bytes_discarded = 0;  // bytes not part of any delivered frame

 private:
  enum Kind { kOk, kIncomplete, kBadHeader, kBadCrc };
  Kind probe(size_t i, size_t* end) const;
  void process();
  void discard(size_t n);

  FrameSink& sink_;
  uint8_t buf_[kMaxFrame + 1] = {};
  size_t len_ = 0;
};

}  // namespace mrctl_fw
