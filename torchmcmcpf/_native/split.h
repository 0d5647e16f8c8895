/* The exported calls' split of samples [0, n) over `threads` OpenMP threads: one part per
 * thread, evenly, so each sample's result is the same whatever the count; on the calling
 * thread when there are fewer than GRAIN samples a thread or no OpenMP. Inside `call`,
 * `lo`, `hi` are the part's samples and `part` its index. */
#ifndef TORCHMCMCPF_SPLIT_H
#define TORCHMCMCPF_SPLIT_H
#include <stdint.h>
#ifdef _OPENMP
#include <omp.h> /* torch's own libgomp when loaded beside it (the same soname): its threads */
#endif

#define GRAIN 8

#ifdef _OPENMP
#define SPLIT(n, threads, call)                                                        \
    {                                                                                  \
        const int64_t n_ = (n);                                                        \
        const int nt_ = (int)(threads), go_ = nt_ > 1 && n_ >= 2 * GRAIN;             \
        _Pragma("omp parallel num_threads(nt_) if (go_)")                              \
        {                                                                              \
            const int64_t t_ = omp_get_thread_num(), T_ = omp_get_num_threads();       \
            const int64_t lo = n_ * t_ / T_, hi = n_ * (t_ + 1) / T_, part = t_;       \
            (void)part;                                                                \
            call;                                                                      \
        }                                                                              \
    }
#else
#define SPLIT(n, threads, call)                 \
    {                                           \
        const int64_t lo = 0, hi = (n), part = 0; \
        (void)part;                             \
        (void)(threads);                        \
        call;                                   \
    }
#endif
#endif
