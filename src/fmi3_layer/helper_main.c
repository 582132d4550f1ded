/* The helper process of an FMU whose model cannot run in its importer's process (remote.h).
 *
 * usage: aaa_cosim_helper FMU_BINARY FD
 * Loads the FMU's own binary, where the model then runs in this process on the runtime the FMU
 * carries, and serves the FMI calls that arrive on the shared memory at descriptor FD.
 */
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>

#include "remote.h"

int main(int argc, char **argv) {
    if (argc != 3) {
        fprintf(stderr, "usage: %s FMU_BINARY FD (started by the FMU itself, not by hand)\n", argv[0]);
        return 64;
    }
    setenv(MODEL_PROCESS_VARIABLE, MODEL_PROCESS_IMPORTER, 1); /* the model runs here, not in yet another helper */
    void *fmu = dlopen(argv[1], RTLD_NOW | RTLD_LOCAL);
    if (!fmu) {
        fprintf(stderr, "aaa_cosim_helper: cannot load %s: %s\n", argv[1], dlerror());
        return 65;
    }
    int (*serve)(int) = (int (*)(int))dlsym(fmu, SERVE_SYMBOL);
    if (!serve) {
        fprintf(stderr, "aaa_cosim_helper: %s has no %s: the FMU and its helper are from different builds\n",
                argv[1], SERVE_SYMBOL);
        return 66;
    }
    return serve(atoi(argv[2]));
}
