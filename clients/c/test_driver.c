/*
 * test_driver.c: drives ftsensord.h for tests/test_c_client.py. Written in the common
 * subset of C11 and C++17 so that the same file is built as C and as C++.
 *
 *   test_driver constants           the header's flag and libzmq constants, "NAME VALUE"
 *   test_driver decode HEX          fts_decode one frame given in hex; prints the result
 *   test_driver track SEQ...        fts_track each sequence number; prints skipped/restarted
 *   test_driver sub ENDPOINT TOPIC  subscribe; then per stdin line: "take" (fts_latest),
 *                                   "wait MS" (fts_wait), "stale SECONDS"
 *                                   (fts_set_stale_after) or "quit"; prints each result
 *                                   with the stale limit then in force and, after the
 *                                   sample, its sigma (fts_reading.sigma)
 *   test_driver staleness           FTS_STALE_PERIODS, _MIN_S, _FIRST_S, FTS_PERIOD_SPAN as compiled
 */
#define _POSIX_C_SOURCE 200809L

#include "ftsensord.h"

#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static void print_sample(const fts_sample *s)
{
    printf(" seq=%" PRIu64 " kind=%u flags=0x%" PRIx32 " t_mono=%.17g t_wall=%.17g count=%u values=", s->seq,
           (unsigned)s->kind, s->flags, s->t_mono, s->t_wall, (unsigned)s->count);
    for (unsigned k = 0; k < s->count; ++k) printf("%s%.17g", k ? "," : "", s->values[k]);
}

static int hex_value(char c)
{
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
}

static int cmd_decode(const char *hex)
{
    size_t n = strlen(hex) / 2;
    /* One byte more than the frame and the frame at an odd address: the decoder must
     * cope with any alignment (a frame's values sit at topic length + 41). */
    unsigned char *buf = (unsigned char *)malloc(n + 1);
    if (buf == NULL) return 1;
    unsigned char *frame = buf + 1;
    for (size_t i = 0; i < n; ++i) {
        int hi = hex_value(hex[2 * i]), lo = hex_value(hex[2 * i + 1]);
        if (hi < 0 || lo < 0) {
            free(buf);
            return 2;
        }
        frame[i] = (unsigned char)(hi * 16 + lo);
    }
    fts_sample s;
    memset(&s, 0, sizeof s);
    int rc = fts_decode(frame, n, NULL, 0, &s);
    printf("rc=%d (%s)", rc, fts_strerror(rc));
    if (rc == FTS_OK) print_sample(&s);
    printf("\n");
    free(buf);
    return 0;
}

static int cmd_track(int argc, char **argv)
{
    fts_seq_track t;
    memset(&t, 0, sizeof t);
    for (int i = 0; i < argc; ++i) {
        int restarted = 0;
        uint64_t skipped = fts_track(&t, strtoull(argv[i], NULL, 10), &restarted);
        printf("seq=%s skipped=%" PRIu64 " restarted=%d\n", argv[i], skipped, restarted);
    }
    printf("total missed=%" PRIu64 " restarts=%" PRIu64 "\n", t.missed, t.restarts);
    return 0;
}

static int cmd_sub(const char *endpoint, const char *topic)
{
    fts_sub *sub = (fts_sub *)malloc(sizeof *sub);
    if (sub == NULL) return 1;
    int rc = fts_open(sub, endpoint, topic);
    printf("open rc=%d (%s)\n", rc, fts_strerror(rc));
    fflush(stdout);
    if (rc != FTS_OK) {
        free(sub);
        return 1;
    }
    char line[64];
    while (fgets(line, sizeof line, stdin) != NULL) {
        fts_reading r;
        memset(&r, 0, sizeof r);
        if (strncmp(line, "take", 4) == 0) {
            rc = fts_latest(sub, &r);
        } else if (strncmp(line, "wait ", 5) == 0) {
            rc = fts_wait(sub, &r, atoi(line + 5));
        } else if (strncmp(line, "stale ", 6) == 0) {
            rc = fts_set_stale_after(sub, atof(line + 6));
        } else {
            break;
        }
        printf("rc=%d (%s) fresh=%d missed=%" PRIu64 " restarted=%d age=%.9f silent=%.17g limit=%.17g"
               " period=%.17g received=%" PRIu64 " rejected=%" PRIu64,
               rc, fts_strerror(rc), r.fresh, r.missed, r.restarted, r.age_s, r.silent_s, fts_stale_limit(sub),
               sub->period_s, sub->received, sub->rejected);
        if (rc >= 0 || rc == FTS_E_STALE) { /* FTS_E_STALE fills r too */
            print_sample(&r.sample);
            printf(" sigma=");
            for (int k = 0; k < FTS_SIGMA_COUNT; ++k) printf("%s%.17g", k ? "," : "", r.sigma[k]);
            printf(" sigma_rejected=%" PRIu64, sub->sigma_rejected);
        }
        printf("\n");
        fflush(stdout);
    }
    fts_close(sub);
    free(sub);
    return 0;
}

static int cmd_constants(void)
{
    static const struct { const char *name; long value; } table[] = {
        {"FLAG_CHIP_MISSING", (long)FTS_FLAG_CHIP_MISSING}, {"FLAG_SATURATED", (long)FTS_FLAG_SATURATED},
        {"FLAG_STALE", (long)FTS_FLAG_STALE}, {"FLAG_OVERLOAD", (long)FTS_FLAG_OVERLOAD},
        {"FLAG_DEGRADED", (long)FTS_FLAG_DEGRADED}, {"FLAG_LATE", (long)FTS_FLAG_LATE},
        {"FLAG_INVALID", (long)FTS_FLAG_INVALID}, {"FLAG_FALLBACK", (long)FTS_FLAG_FALLBACK},
        {"FLAG_EXTRAPOLATED", (long)FTS_FLAG_EXTRAPOLATED}, {"FLAG_INCONSISTENT", (long)FTS_FLAG_INCONSISTENT},
        {"FLAG_ORIENTATION_STALE", (long)FTS_FLAG_ORIENTATION_STALE},
        {"FLAG_TEMPERATURE", (long)FTS_FLAG_TEMPERATURE},
        {"MAGIC", (long)FTS_MAGIC},
        {"VERSION", (long)FTS_VERSION}, {"KIND_WRENCH", (long)FTS_KIND_WRENCH},
        {"KIND_FLUX", (long)FTS_KIND_FLUX}, {"KIND_SIGMA", (long)FTS_KIND_SIGMA},
        {"HEADER_SIZE", (long)FTS_HEADER_SIZE},
        {"zmq.PUB", (long)FTS_ZMQ_PUB_}, {"zmq.SUB", (long)FTS_ZMQ_SUB_}, {"zmq.SUBSCRIBE", (long)FTS_ZMQ_SUBSCRIBE_},
        {"zmq.LINGER", (long)FTS_ZMQ_LINGER_}, {"zmq.RCVTIMEO", (long)FTS_ZMQ_RCVTIMEO_},
        {"zmq.CONFLATE", (long)FTS_ZMQ_CONFLATE_}, {"zmq.DONTWAIT", (long)FTS_ZMQ_DONTWAIT_},
        {"errno.EAGAIN", (long)EAGAIN}, {"errno.EINTR", (long)EINTR},
    };
    for (size_t i = 0; i < sizeof table / sizeof table[0]; ++i) {
        const char *flag = fts_flag_name((uint32_t)table[i].value);
        printf("%s %ld %s\n", table[i].name, table[i].value,
               strncmp(table[i].name, "FLAG_", 5) == 0 && flag ? flag : "-");
    }
    return 0;
}

/* Encode the documented orientation test vector (hex), then send N of them to ENDPOINT
 * 10 ms apart, when given. */
static int cmd_orient(int argc, char **argv)
{
    const double h = 0.70710678118654757; /* sqrt(1/2), the double nearest */
    const double q[4] = {h, 0.0, 0.0, h};
    unsigned char m[FTS_ORIENT_SIZE];
    if (fts_orientation_encode(m, "sensor1", q, 12.5) != FTS_OK) return 1;
    for (size_t i = 0; i < sizeof m; ++i) printf("%02x", m[i]);
    printf("\n");
    if (argc < 2) return 0;
    fts_orient p;
    if (fts_orientation_open(&p, argv[0]) != FTS_OK) return 1;
    const struct timespec tick = {0, 10000000L};
    for (int i = 0, n = atoi(argv[1]); i < n; ++i) {
        if (fts_orientation_send(&p, "sensor1", q, 12.5) != FTS_OK) return 1;
        nanosleep(&tick, NULL);
    }
    fts_orientation_close(&p);
    return 0;
}

int main(int argc, char **argv)
{
    if (argc >= 2 && strcmp(argv[1], "orient") == 0) return cmd_orient(argc - 2, argv + 2);
    if (argc >= 2 && strcmp(argv[1], "constants") == 0) return cmd_constants();
    if (argc >= 2 && strcmp(argv[1], "staleness") == 0) {
        printf("periods=%.17g min=%.17g first=%.17g span=%u\n", FTS_STALE_PERIODS, FTS_STALE_MIN_S, FTS_STALE_FIRST_S,
               (unsigned)FTS_PERIOD_SPAN);
        return 0;
    }
    if (argc == 3 && strcmp(argv[1], "decode") == 0) return cmd_decode(argv[2]);
    if (argc >= 2 && strcmp(argv[1], "track") == 0) return cmd_track(argc - 2, argv + 2);
    if (argc == 4 && strcmp(argv[1], "sub") == 0) return cmd_sub(argv[2], argv[3]);
    fprintf(stderr, "usage: %s constants | staleness | decode HEX | track SEQ... | sub ENDPOINT TOPIC | orient [ENDPOINT N]\n",
            argv[0]);
    return 2;
}
