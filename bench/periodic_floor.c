/* The machine's own wake-up latency floor: a C loop sleeping to absolute deadlines
 * (clock_nanosleep TIMER_ABSTIME on CLOCK_MONOTONIC), the same measurement the Python
 * frame loop makes. Usage: periodic_floor RATE_HZ SECONDS. Prints one latency in ns
 * per line. Built by bench/bench_loop.py with the system's cc; a stand-in for
 * cyclictest (rt-tests) when that is not installed. */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

static long long ns(const struct timespec *t) { return t->tv_sec * 1000000000LL + t->tv_nsec; }

int main(int argc, char **argv) {
    if (argc != 3) { fprintf(stderr, "usage: %s RATE_HZ SECONDS\n", argv[0]); return 2; }
    double rate = atof(argv[1]), secs = atof(argv[2]);
    long long period = (long long)(1e9 / rate), n = (long long)(rate * secs);
    struct timespec t0, now, dl;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (long long k = 1; k <= n; k++) {
        long long d = ns(&t0) + k * period;
        dl.tv_sec = d / 1000000000LL; dl.tv_nsec = d % 1000000000LL;
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &dl, NULL);
        clock_gettime(CLOCK_MONOTONIC, &now);
        printf("%lld\n", ns(&now) - d);
    }
    return 0;
}
