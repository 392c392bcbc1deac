// A CUDA profile of a whole program through CUPTI, loaded by the driver as an injection library:
//
//   CUDA_INJECTION64_PATH=/path/libdex2hoi-profile.so DEX2HOI_PROFILE_OUT=profile.json PROGRAM...
//
// It counts, from the program's first CUDA call to its exit: the kernels the GPU ran (those of
// cuBLAS included) with their summed duration and the time the GPU was busy with at least one
// (the union of their intervals), the copies and fills, and the driver calls by name (launches,
// allocations, frees, event records, synchronisations). The JSON written at exit also has the
// wall time and the kernels that took the most time. Two runs of different lengths give the
// figures per training step by difference (`scripts/gpu-check.sh`). `cargo xtask build-cuda`
// compiles it against the CUPTI of the CUDA 13.0 wheels; at run time it needs `libcupti.so.13`
// on the library path (PyTorch's wheels have it).
#include <cupti.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define BUFFER_BYTES (8u << 20)
#define NAME_SLOTS 16384
#define DRIVER_CALLS 4096
#define TOP 12

typedef struct {
    uint64_t start, end;
} Interval;

typedef struct {
    char *name;
    uint64_t count, nanoseconds;
} KernelName;

static Interval *intervals;
static size_t interval_count, interval_capacity;
static uint64_t kernel_nanoseconds;
#define COPY_KINDS 16
static uint64_t copies[COPY_KINDS], copied_bytes[COPY_KINDS], fills, dropped;
static KernelName names[NAME_SLOTS];
static uint64_t driver_calls[DRIVER_CALLS];
static uint64_t wall_start;
static CUpti_SubscriberHandle subscriber;

static uint64_t now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (uint64_t)t.tv_sec * 1000000000u + (uint64_t)t.tv_nsec;
}

static void add_interval(uint64_t start, uint64_t end) {
    if (interval_count == interval_capacity) {
        interval_capacity = interval_capacity ? 2 * interval_capacity : 1u << 16;
        intervals = realloc(intervals, interval_capacity * sizeof *intervals);
        if (!intervals) abort();
    }
    intervals[interval_count++] = (Interval){start, end};
}

static void add_name(const char *name, uint64_t nanoseconds) {
    if (!name) name = "?";
    uint64_t hash = 1469598103934665603u;
    for (const char *c = name; *c; c++) hash = (hash ^ (uint8_t)*c) * 1099511628211u;
    for (size_t probe = 0; probe < NAME_SLOTS; probe++) {
        KernelName *slot = &names[(hash + probe) % NAME_SLOTS];
        if (!slot->name) {
            slot->name = strdup(name);
            if (!slot->name) abort();
        }
        if (strcmp(slot->name, name) == 0) {
            slot->count++;
            slot->nanoseconds += nanoseconds;
            return;
        }
    }
}

static void CUPTIAPI buffer_requested(uint8_t **buffer, size_t *size, size_t *most_records) {
    *buffer = aligned_alloc(8, BUFFER_BYTES);
    *size = *buffer ? BUFFER_BYTES : 0;
    *most_records = 0;
}

static void CUPTIAPI buffer_completed(CUcontext context, uint32_t stream, uint8_t *buffer,
                                      size_t size, size_t valid) {
    (void)context;
    (void)stream;
    (void)size;
    CUpti_Activity *record = NULL;
    while (cuptiActivityGetNextRecord(buffer, valid, &record) == CUPTI_SUCCESS) {
        if (record->kind == CUPTI_ACTIVITY_KIND_CONCURRENT_KERNEL) {
            const CUpti_ActivityKernel10 *k = (const CUpti_ActivityKernel10 *)record;
            kernel_nanoseconds += k->end - k->start;
            add_interval(k->start, k->end);
            add_name(k->name, k->end - k->start);
        } else if (record->kind == CUPTI_ACTIVITY_KIND_MEMCPY) {
            const CUpti_ActivityMemcpy6 *m = (const CUpti_ActivityMemcpy6 *)record;
            copies[m->copyKind % COPY_KINDS]++;
            copied_bytes[m->copyKind % COPY_KINDS] += m->bytes;
            add_interval(m->start, m->end);
        } else if (record->kind == CUPTI_ACTIVITY_KIND_MEMSET) {
            const CUpti_ActivityMemset4 *m = (const CUpti_ActivityMemset4 *)record;
            fills++;
            add_interval(m->start, m->end);
        }
    }
    size_t lost = 0;
    if (cuptiActivityGetNumDroppedRecords(context, stream, &lost) == CUPTI_SUCCESS)
        dropped += lost;
    free(buffer);
}

static void CUPTIAPI on_callback(void *user, CUpti_CallbackDomain domain, CUpti_CallbackId id,
                                 const void *data) {
    (void)user;
    if (domain == CUPTI_CB_DOMAIN_DRIVER_API) {
        const CUpti_CallbackData *call = data;
        if (call->callbackSite == CUPTI_API_ENTER && id < DRIVER_CALLS)
            __atomic_add_fetch(&driver_calls[id], 1, __ATOMIC_RELAXED);
    } else if (domain == CUPTI_CB_DOMAIN_RESOURCE &&
               id == CUPTI_CBID_RESOURCE_CONTEXT_DESTROY_STARTING) {
        // The context's records, before it goes.
        cuptiActivityFlushAll(CUPTI_ACTIVITY_FLAG_FLUSH_FORCED);
    }
}

static int by_start(const void *a, const void *b) {
    const Interval *x = a, *y = b;
    return (x->start > y->start) - (x->start < y->start);
}

static int by_time(const void *a, const void *b) {
    const KernelName *x = a, *y = b;
    return (x->nanoseconds < y->nanoseconds) - (x->nanoseconds > y->nanoseconds);
}

static void json_string(FILE *out, const char *text) {
    fputc('"', out);
    for (const char *c = text; *c; c++) {
        if (*c == '"' || *c == '\\') fputc('\\', out);
        if ((unsigned char)*c >= 0x20) fputc(*c, out);
    }
    fputc('"', out);
}

static void report(void) {
    cuptiActivityFlushAll(CUPTI_ACTIVITY_FLAG_FLUSH_FORCED);
    double wall = (double)(now() - wall_start) * 1e-9;
    qsort(intervals, interval_count, sizeof *intervals, by_start);
    uint64_t busy = 0, reach = 0;
    for (size_t i = 0; i < interval_count; i++) {
        uint64_t start = intervals[i].start > reach ? intervals[i].start : reach;
        if (intervals[i].end > start) busy += intervals[i].end - start;
        if (intervals[i].end > reach) reach = intervals[i].end;
    }
    uint64_t kernels = 0;
    for (size_t i = 0; i < NAME_SLOTS; i++) kernels += names[i].count;
    qsort(names, NAME_SLOTS, sizeof *names, by_time);
    const char *path = getenv("DEX2HOI_PROFILE_OUT");
    FILE *out = path ? fopen(path, "w") : stderr;
    if (!out) out = stderr;
    fprintf(out, "{\"wall_s\": %.6f, \"kernels\": %llu, \"kernel_s\": %.9f, \"busy_s\": %.9f,\n",
            wall, (unsigned long long)kernels, (double)kernel_nanoseconds * 1e-9,
            (double)busy * 1e-9);
    fprintf(out,
            " \"copies_host_to_device\": %llu, \"bytes_host_to_device\": %llu, "
            "\"copies_device_to_host\": %llu, \"bytes_device_to_host\": %llu,\n"
            " \"copies_device_to_device\": %llu, \"fills\": %llu, \"dropped_records\": %llu,\n",
            (unsigned long long)copies[CUPTI_ACTIVITY_MEMCPY_KIND_HTOD],
            (unsigned long long)copied_bytes[CUPTI_ACTIVITY_MEMCPY_KIND_HTOD],
            (unsigned long long)copies[CUPTI_ACTIVITY_MEMCPY_KIND_DTOH],
            (unsigned long long)copied_bytes[CUPTI_ACTIVITY_MEMCPY_KIND_DTOH],
            (unsigned long long)copies[CUPTI_ACTIVITY_MEMCPY_KIND_DTOD],
            (unsigned long long)fills, (unsigned long long)dropped);
    fprintf(out, " \"driver_calls\": {");
    int first = 1;
    for (uint32_t id = 0; id < DRIVER_CALLS; id++) {
        if (!driver_calls[id]) continue;
        const char *name = NULL;
        if (cuptiGetCallbackName(CUPTI_CB_DOMAIN_DRIVER_API, id, &name) != CUPTI_SUCCESS || !name)
            continue;
        fprintf(out, "%s", first ? "" : ", ");
        json_string(out, name);
        fprintf(out, ": %llu", (unsigned long long)driver_calls[id]);
        first = 0;
    }
    fprintf(out, "},\n \"top_kernels\": [");
    for (size_t i = 0; i < TOP && names[i].name; i++) {
        fprintf(out, "%s\n  [", i ? "," : "");
        json_string(out, names[i].name);
        fprintf(out, ", %llu, %.9f]", (unsigned long long)names[i].count,
                (double)names[i].nanoseconds * 1e-9);
    }
    fprintf(out, "]}\n");
    if (out != stderr) fclose(out);
}

// Called by the CUDA driver at `cuInit` when CUDA_INJECTION64_PATH names this library.
int InitializeInjection(void) {
    wall_start = now();
    if (cuptiActivityRegisterCallbacks(buffer_requested, buffer_completed) != CUPTI_SUCCESS ||
        cuptiActivityEnable(CUPTI_ACTIVITY_KIND_CONCURRENT_KERNEL) != CUPTI_SUCCESS ||
        cuptiActivityEnable(CUPTI_ACTIVITY_KIND_MEMCPY) != CUPTI_SUCCESS ||
        cuptiActivityEnable(CUPTI_ACTIVITY_KIND_MEMSET) != CUPTI_SUCCESS ||
        cuptiSubscribe(&subscriber, on_callback, NULL) != CUPTI_SUCCESS ||
        cuptiEnableDomain(1, subscriber, CUPTI_CB_DOMAIN_DRIVER_API) != CUPTI_SUCCESS ||
        cuptiEnableDomain(1, subscriber, CUPTI_CB_DOMAIN_RESOURCE) != CUPTI_SUCCESS) {
        fprintf(stderr, "dex2hoi-profile: CUPTI could not be set up\n");
        return 0;
    }
    atexit(report);
    return 1;
}
