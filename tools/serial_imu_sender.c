/*
 * Kestrel VIO serial IMU protocol: reference frame encoder for microcontroller firmware.
 * Copy kestrel_imu_frame() and kestrel_crc16() into the firmware; send the 40 bytes over the UART.
 * Spec: docs/serial-imu.md. The test suite compiles this file (with -DKESTREL_SENDER_MAIN) and checks
 * that its frames are byte-identical to drivers/serial_protocol.py.
 *
 * Frame, little endian: A5 5A | len=32 | type=0x01 | seq u16 | t_us u64 | gyro i32[3] (1e-6 rad/s)
 *                       | accel i32[3] (1e-5 m/s^2) | crc16 (CCITT-FALSE over len..payload)
 *
 * Stamp t_us with the microcontroller's timer AT THE IMU SAMPLE (data-ready interrupt), not at send time;
 * the host estimates offset and drift of that clock.
 */
#include <stdint.h>
#include <stddef.h>

#define KESTREL_IMU_FRAME_SIZE 40

/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor. */
uint16_t kestrel_crc16(const uint8_t *data, size_t n) {
    uint16_t crc = 0xFFFF;
    for (size_t i = 0; i < n; ++i) {
        crc ^= (uint16_t)data[i] << 8;
        for (int b = 0; b < 8; ++b)
            crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
    }
    return crc;
}

static void put_le(uint8_t *p, uint64_t v, int nbytes) {
    for (int i = 0; i < nbytes; ++i) p[i] = (uint8_t)(v >> (8 * i));
}

/* gyro in 1e-6 rad/s, accel in 1e-5 m/s^2, already scaled and rounded by the caller (the IMU's raw
 * counts times its datasheet scale), in the IMU frame that the calibration calls `body`. */
void kestrel_imu_frame(uint8_t out[KESTREL_IMU_FRAME_SIZE], uint16_t seq, uint64_t t_us,
                       const int32_t gyro[3], const int32_t accel[3]) {
    out[0] = 0xA5;
    out[1] = 0x5A;
    out[2] = 32;   /* payload length */
    out[3] = 0x01; /* type: IMU */
    put_le(out + 4, seq, 2);
    put_le(out + 6, t_us, 8);
    for (int i = 0; i < 3; ++i) put_le(out + 14 + 4 * i, (uint32_t)gyro[i], 4);
    for (int i = 0; i < 3; ++i) put_le(out + 26 + 4 * i, (uint32_t)accel[i], 4);
    uint16_t crc = kestrel_crc16(out + 2, 36);
    put_le(out + 38, crc, 2);
}

#ifdef KESTREL_SENDER_MAIN
/* Host test driver: reads "seq t_us gx gy gz ax ay az" lines (integers), writes frames as hex lines. */
#include <stdio.h>
int main(void) {
    unsigned seq;
    unsigned long long t_us;
    long g[3], a[3];
    while (scanf("%u %llu %ld %ld %ld %ld %ld %ld", &seq, &t_us, &g[0], &g[1], &g[2], &a[0], &a[1], &a[2]) == 8) {
        int32_t gi[3] = {(int32_t)g[0], (int32_t)g[1], (int32_t)g[2]};
        int32_t ai[3] = {(int32_t)a[0], (int32_t)a[1], (int32_t)a[2]};
        uint8_t f[KESTREL_IMU_FRAME_SIZE];
        kestrel_imu_frame(f, (uint16_t)seq, t_us, gi, ai);
        for (int i = 0; i < KESTREL_IMU_FRAME_SIZE; ++i) printf("%02x", f[i]);
        printf("\n");
    }
    return 0;
}
#endif
