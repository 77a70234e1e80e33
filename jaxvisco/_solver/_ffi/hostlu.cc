// XLA foreign-function targets for jaxvisco's host sparse LU (see jaxvisco/_solver/_sparse.py).
//
// Why an extension: a `jax.pure_callback` makes JAX refuse to write the program to its
// persistent compilation cache (the callback is a Python object inside the program), so
// every process paid the full XLA compilation of the time loop (10-28 s). These two
// targets are referred to by name, so the programs that use them are cached. They do
// no numerical work themselves: each call hands its buffers (zero-copy memoryviews) to
// one Python callable registered by jaxvisco, which runs SuperLU (scipy) exactly as the
// callback path does.
//
//   jaxvisco_lu_factor: attrs key; arg data f64[nnz]      -> token s64[]
//   jaxvisco_lu_solve:  attrs key, trans; args token s64[], b f64[n] -> x f64[n]
//
// The callable is called as callable(op, key, token, src, dst) with op 0 (factor),
// 1 (solve) or 2 (solve with the transposed factors); it writes its result into dst.

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <cstdint>
#include <string>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

static PyObject* g_callable = nullptr;  // owned reference, set by set_callable()

static ffi::Error CallPython(int64_t op, int64_t key, int64_t token, void* src, size_t src_bytes, void* dst,
                             size_t dst_bytes) {
  if (!Py_IsInitialized()) return ffi::Error(ffi::ErrorCode::kInternal, "jaxvisco: Python is not running");
  PyGILState_STATE gil = PyGILState_Ensure();
  std::string message;
  if (g_callable == nullptr) {
    message = "jaxvisco: the host LU callable is not registered (import jaxvisco first)";
  } else {
    PyObject* in = PyMemoryView_FromMemory(static_cast<char*>(src), static_cast<Py_ssize_t>(src_bytes), PyBUF_READ);
    PyObject* out = PyMemoryView_FromMemory(static_cast<char*>(dst), static_cast<Py_ssize_t>(dst_bytes), PyBUF_WRITE);
    PyObject* result = nullptr;
    if (in != nullptr && out != nullptr) {
      result = PyObject_CallFunction(g_callable, "LLLOO", static_cast<long long>(op), static_cast<long long>(key),
                                     static_cast<long long>(token), in, out);
    }
    if (result == nullptr) {
      PyObject *type, *value, *trace;
      PyErr_Fetch(&type, &value, &trace);
      PyObject* text = value != nullptr ? PyObject_Str(value) : nullptr;
      const char* utf8 = text != nullptr ? PyUnicode_AsUTF8(text) : nullptr;
      message = utf8 != nullptr ? utf8 : "jaxvisco: the host LU callable raised an exception";
      Py_XDECREF(text);
      Py_XDECREF(type);
      Py_XDECREF(value);
      Py_XDECREF(trace);
      PyErr_Clear();
    }
    Py_XDECREF(result);
    Py_XDECREF(in);
    Py_XDECREF(out);
  }
  PyGILState_Release(gil);
  if (!message.empty()) return ffi::Error(ffi::ErrorCode::kInternal, message);
  return ffi::Error::Success();
}

// Factor: `retain` (how many factorizations the pattern's store keeps alive, at least)
// travels to Python in the token slot, which a factorization does not use.
static ffi::Error Factor(int64_t key, int64_t retain, ffi::Buffer<ffi::F64> data, ffi::ResultBufferR0<ffi::S64> token) {
  return CallPython(0, key, retain, data.typed_data(), data.size_bytes(), token->typed_data(), sizeof(int64_t));
}

static ffi::Error Solve(int64_t key, int64_t trans, ffi::BufferR0<ffi::S64> token, ffi::Buffer<ffi::F64> b,
                        ffi::ResultBuffer<ffi::F64> x) {
  return CallPython(trans ? 2 : 1, key, *token.typed_data(), b.typed_data(), b.size_bytes(), x->typed_data(),
                    x->size_bytes());
}

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxviscoLuFactor, Factor,
                              ffi::Ffi::Bind()
                                  .Attr<int64_t>("key")
                                  .Attr<int64_t>("retain")
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Ret<ffi::BufferR0<ffi::S64>>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxviscoLuSolve, Solve,
                              ffi::Ffi::Bind()
                                  .Attr<int64_t>("key")
                                  .Attr<int64_t>("trans")
                                  .Arg<ffi::BufferR0<ffi::S64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Ret<ffi::Buffer<ffi::F64>>());

// ------------------------------------------------------------------ Python module

static PyObject* set_callable(PyObject*, PyObject* fn) {
  if (!PyCallable_Check(fn)) {
    PyErr_SetString(PyExc_TypeError, "set_callable needs a callable");
    return nullptr;
  }
  Py_INCREF(fn);
  Py_XSETREF(g_callable, fn);
  Py_RETURN_NONE;
}

static PyObject* capsule(void* fn) { return PyCapsule_New(fn, nullptr, nullptr); }
static PyObject* factor_target(PyObject*, PyObject*) { return capsule(reinterpret_cast<void*>(JaxviscoLuFactor)); }
static PyObject* solve_target(PyObject*, PyObject*) { return capsule(reinterpret_cast<void*>(JaxviscoLuSolve)); }

static PyMethodDef kMethods[] = {
    {"set_callable", set_callable, METH_O, "Register the Python callable that does the host LU work."},
    {"factor_target", factor_target, METH_NOARGS, "Capsule of the jaxvisco_lu_factor FFI handler."},
    {"solve_target", solve_target, METH_NOARGS, "Capsule of the jaxvisco_lu_solve FFI handler."},
    {nullptr, nullptr, 0, nullptr}};

static struct PyModuleDef kModule = {PyModuleDef_HEAD_INIT, "_hostlu", "jaxvisco's host sparse LU as XLA FFI targets",
                                     -1, kMethods};

PyMODINIT_FUNC PyInit__hostlu(void) { return PyModule_Create(&kModule); }
