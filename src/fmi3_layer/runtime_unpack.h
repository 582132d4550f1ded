/* The Python runtime an FMU carries (orchestration/portable_runtime.py), unpacked once per machine.
 *
 * The runtime is ~350 MB of files, ~130 MB compressed. Importers extract an FMU to a new folder on
 * every load (FMPy's simulate_fmu on every call); carried as loose files it would be inflated and
 * written there each time. So the FMU carries it as one archive, resources/runtime.zip (stored, not
 * compressed again, in the FMU), named by resources/runtime.id (the digest of its content), and the
 * FMI layer unpacks it on first use into a folder named by that digest:
 *   $AAA_COSIM_RUNTIME_CACHE/<id>, else $XDG_CACHE_HOME/aaa-cosim/runtime/<id>,
 *   else $HOME/.cache/aaa-cosim/runtime/<id>; where none can be written, <resources>/runtime.
 * A folder is complete or absent: it is unpacked under a temporary name and renamed into place,
 * so concurrent first loads (two processes, two instances) never see half a runtime.
 * Inflating needs zlib (libz.so.1, on every Linux distribution); it is loaded at run time.
 */
#ifndef AAA_RUNTIME_UNPACK_H
#define AAA_RUNTIME_UNPACK_H

#include <stddef.h>

/* 1 when resources/runtime.zip exists (the FMU carries a runtime), else 0. */
int runtime_carried(const char *resource_dir);

/* The folder of the unpacked runtime in `folder` (unpacked now if needed). Returns 0, or -1 with a
 * reason naming what is missing and how to provide it. */
int runtime_folder(const char *resource_dir, char *folder, size_t folder_size, char *reason, size_t reason_size);

#endif
