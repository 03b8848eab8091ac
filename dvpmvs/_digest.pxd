# The digest of the kernel's own source, set by setup.py for each extension (see
# dvpmvs/_kernel_sources.py); empty when a kernel is compiled some other way.
cdef extern from *:
    """
    #ifndef DVPMVS_SOURCE_DIGEST
    #define DVPMVS_SOURCE_DIGEST ""
    #endif
    """
    const char *DVPMVS_SOURCE_DIGEST
