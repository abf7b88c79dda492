// Declarations of the Teensyduino API the Teensy 4.x board file uses, with the
// signatures of the Teensy 4 core (cores/teensy4), so tests/test_firmware.py
// can compile the board file with the system's g++ (-fsyntax-only: nothing is
// linked or run). Not an emulation; a typo or a wrong call fails the test.
#pragma once

#include <stddef.h>
#include <stdint.h>

#define HIGH 1
#define LOW 0
#define INPUT 0
#define OUTPUT 1
#define INPUT_PULLUP 2

int analogRead(uint8_t pin);
void analogReadResolution(unsigned int bits);
void analogReadAveraging(unsigned int num);
void analogWrite(uint8_t pin, int val);
uint32_t analogWriteResolution(uint32_t bits);
void analogWriteFrequency(uint8_t pin, float frequency);
void pinMode(uint8_t pin, uint8_t mode);
void digitalWriteFast(uint8_t pin, uint8_t val);
uint8_t digitalReadFast(uint8_t pin);
void digitalToggleFast(uint8_t pin);
uint32_t micros(void);
void noInterrupts();
void interrupts();

class IntervalTimer {
 public:
  bool begin(void (*funct)(), float microseconds);
  void priority(uint8_t n);
};

class usb_serial_class {
 public:
  void begin(long baud);
  int available();
  int availableForWrite();
  size_t readBytes(char* buffer, size_t length);
  size_t write(const uint8_t* buffer, size_t size);
  void send_now();
};
extern usb_serial_class Serial;
