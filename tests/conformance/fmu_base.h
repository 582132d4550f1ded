/* Types the conformance FMUs' models are written with; included first by each model file, which
   then defines its `Model` struct and includes fmu_common.h. */
#ifndef FMU_BASE_H
#define FMU_BASE_H

#include <math.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi3Functions.h"

#define MAX_VARIABLES 40
#define MAX_TEXT 256

typedef enum { MODE_INSTANTIATED, MODE_CONFIGURATION, MODE_INITIALIZATION, MODE_STEP, MODE_TERMINATED,
               MODE_ERROR } Mode;
static const char *MODE_NAMES[] = {"Instantiated", "Configuration", "Initialization", "Step", "Terminated", "Error"};

typedef enum { V_FLOAT32, V_FLOAT64, V_INT8, V_UINT8, V_INT16, V_UINT16, V_INT32, V_UINT32, V_INT64, V_UINT64,
               V_BOOLEAN, V_ENUMERATION, V_STRING, V_BINARY } VarType;
static const char *TYPE_NAMES[] = {"Float32", "Float64", "Int8", "UInt8", "Int16", "UInt16", "Int32", "UInt32",
                                   "Int64", "UInt64", "Boolean", "Enumeration", "String", "Binary"};

typedef enum { C_PARAMETER, C_STRUCTURAL, C_INPUT, C_OUTPUT, C_CALCULATED } Causality;

typedef struct { char text[MAX_TEXT]; } Text;                 /* a String value */
typedef struct { uint8_t bytes[MAX_TEXT]; size_t size; } Blob; /* a Binary value */

#endif
