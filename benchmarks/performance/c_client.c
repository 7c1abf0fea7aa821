/*
 * c_client.c: what one fts_latest call costs a 1 kHz haptic loop. Built and run by
 * benchmarks/performance/c_client.py, which starts the daemon and reads the output.
 *
 *     c_client ENDPOINT TOPIC TICKS
 *
 * Waits for the first sample, then runs TICKS ticks at 1 kHz (absolute deadlines) and
 * prints one line a tick: "call_ns fresh age_ns" (the call's duration on CLOCK_MONOTONIC,
 * whether it returned a new sample, and that sample's age then), and finally the cost of
 * the two clock reads alone ("timer_ns" lines, as many), which the call's figure includes.
 */
#define _POSIX_C_SOURCE 200809L

#include "ftsensord.h"

#include <stdio.h>
#include <stdlib.h>

static long long ns_between(const struct timespec *a, const struct timespec *b)
{
    return (long long)(b->tv_sec - a->tv_sec) * 1000000000LL + (b->tv_nsec - a->tv_nsec);
}

int main(int argc, char **argv)
{
    if (argc != 4) {
        fprintf(stderr, "usage: %s ENDPOINT TOPIC TICKS\n", argv[0]);
        return 2;
    }
    long ticks = atol(argv[3]);
    fts_sub sub;
    fts_reading r;
    int rc = fts_open(&sub, argv[1], argv[2]);
    if (rc == FTS_OK) rc = fts_wait(&sub, &r, 10000);
    if (rc < 0) {
        fprintf(stderr, "no sample from %s %s: %s\n", argv[1], argv[2], fts_strerror(rc));
        return 1;
    }
    long long *call = (long long *)malloc(sizeof(long long) * (size_t)ticks * 2);
    long long *age = call + ticks;
    char *fresh = (char *)calloc((size_t)ticks, 1);
    if (call == NULL || fresh == NULL) return 1;
    struct timespec next, t0, t1;
    clock_gettime(CLOCK_MONOTONIC, &next);
    for (long i = 0; i < ticks; ++i) {
        clock_gettime(CLOCK_MONOTONIC, &t0);
        rc = fts_latest(&sub, &r);
        clock_gettime(CLOCK_MONOTONIC, &t1);
        call[i] = ns_between(&t0, &t1);
        fresh[i] = rc == FTS_NEW;
        age[i] = rc >= 0 ? (long long)(r.age_s * 1e9) : -1;
        next.tv_nsec += 1000000L;
        if (next.tv_nsec >= 1000000000L) {
            next.tv_nsec -= 1000000000L;
            next.tv_sec++;
        }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
    }
    for (long i = 0; i < ticks; ++i) printf("%lld %d %lld\n", call[i], fresh[i], age[i]);
    for (long i = 0; i < ticks; ++i) {
        clock_gettime(CLOCK_MONOTONIC, &t0);
        clock_gettime(CLOCK_MONOTONIC, &t1);
        printf("timer_ns %lld\n", ns_between(&t0, &t1));
    }
    fprintf(stderr, "rejected %llu, missed %llu\n", (unsigned long long)sub.rejected,
            (unsigned long long)sub.track.missed);
    free(call);
    free(fresh);
    fts_close(&sub);
    return 0;
}
