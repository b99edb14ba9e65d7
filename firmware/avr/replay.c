/* ATmega128 test program (not part of the library): firmware/host/replay.c's stream through the
 * anchor KF under simavr. The stream (anchor_config, then 'I' + anchor_imu_in or 'G' +
 * anchor_gnss_in records, the struct bytes of a float32 build: every member is 4 bytes, so the
 * layout is the host's) is compiled into flash by the test (`stream.c`, anchor_stream[], at most
 * 32 KB: the AVR's object size limit). Prints on UART0 one line per record: "O" and the hex
 * bytes of the anchor_output_t for an IMU record, "G" and the return code for a GNSS record,
 * then "done". */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/pgmspace.h>
#include <string.h>

#include "../anchor.h"

extern const uint8_t anchor_stream[] PROGMEM;
extern const uint16_t anchor_stream_len;

static void putch(char c)
{
    while (!(UCSR0A & (1 << UDRE0))) {
    }
    UDR0 = (uint8_t)c;
}

static void put_hex(const void *p, uint16_t n)
{
    static const char digits[] = "0123456789abcdef";
    const uint8_t *b = (const uint8_t *)p;
    while (n--) {
        putch(digits[*b >> 4]);
        putch(digits[*b & 15]);
        ++b;
    }
}

int main(void)
{
    static anchor_state st;
    anchor_config cfg;
    anchor_imu_in imu;
    anchor_gnss_in gnss;
    anchor_output_t out;
    uint16_t pos = sizeof cfg;
    int32_t rc;
    UBRR0H = 0;
    UBRR0L = 0;
    UCSR0A = (1 << U2X0); /* 1 Mbaud at 8 MHz */
    UCSR0B = (1 << TXEN0);
    memcpy_P(&cfg, anchor_stream, sizeof cfg);
    rc = anchor_init(&st, &cfg);
    while (rc == ANCHOR_OK && pos < anchor_stream_len) {
        char kind = (char)pgm_read_byte(anchor_stream + pos);
        ++pos;
        if (kind == 'I') {
            memcpy_P(&imu, anchor_stream + pos, sizeof imu);
            pos += sizeof imu;
            rc = anchor_step_imu(&st, &imu);
            anchor_output(&st, &out);
            putch('O');
            put_hex(&out, sizeof out);
        } else {
            memcpy_P(&gnss, anchor_stream + pos, sizeof gnss);
            pos += sizeof gnss;
            putch('G');
            put_hex(&(int32_t){anchor_step_gnss(&st, &gnss)}, 4);
        }
        putch('\n');
    }
    if (rc == ANCHOR_OK) {
        putch('d');
        putch('o');
        putch('n');
        putch('e');
        putch('\n');
    }
    cli();
    for (;;) {
        __asm__ __volatile__("sleep"); /* simavr: sleep with interrupts off ends the simulation */
    }
}
