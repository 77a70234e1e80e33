// XLA foreign-function targets for jaxvisco's host sparse LU (see jaxvisco/_solver/_sparse.py).
//
// Why an extension: a `jax.pure_callback` makes JAX refuse to write the program to its
// persistent compilation cache (the callback is a Python object inside the program), so
// every process paid the full XLA compilation of the time loop (10-28 s). These two
// targets are referred to by name, so the programs that use them are cached.
//
//   jaxvisco_lu_factor: attrs key, retain; arg data f64[nnz] -> token s64[]
//   jaxvisco_lu_solve:  attrs key, trans; args token s64[], b f64[n] -> x f64[n]
//
// Factoring is SuperLU's (scipy), in Python: the factor target hands its buffers
// (zero-copy memoryviews) to one Python callable registered by jaxvisco, called as
// callable(op, key, token, src, dst) with op 0 (factor), 1 (solve) or 2 (transposed
// solve); it writes its result into dst. Python then publishes the triangular factors
// here (`publish`), and solves with a published factorization run in C++ below: no
// Python, no GIL. Measured (2D L-shape refinement 4, n = 1378, 78 606 nonzeros in L and
// U): one solve through the Python callable cost 255 us in a compiled loop (SuperLU's
// own solve 98 us of it). Solves with a factorization that is not published (none is
// where Python keeps SuperLU's object) go to the Python callable.

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <cstdint>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

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

// ------------------------------------------------------------------ published factors
//
// P_r A P_c = L U (scipy's SuperLU: (P_r b)[perm_r[i]] = b[i], (P_c w)[i] = w[perm_c[i]]),
// L unit lower, U upper; both kept as compressed columns without their diagonals
// (U's diagonal apart).
struct Factors {
  int64_t n = 0;
  std::vector<int64_t> lp, up;   // column pointers, n + 1
  std::vector<int32_t> li, ui;   // row indices: L strictly below, U strictly above the diagonal
  std::vector<double> lx, ux, ud;
  std::vector<int32_t> pr, pc;   // SuperLU's perm_r, perm_c
  mutable std::atomic<uint64_t> last_use{0};  // g_clock at its publication or latest solve
};

static std::atomic<uint64_t> g_clock{0};

static std::mutex g_mutex;
static std::map<std::pair<int64_t, int64_t>, std::shared_ptr<const Factors>> g_store;  // (key, token)

// The published factorization (key, token), marked as used now; null where there is none.
static std::shared_ptr<const Factors> Lookup(int64_t key, int64_t token) {
  std::lock_guard<std::mutex> lock(g_mutex);
  auto it = g_store.find({key, token});
  if (it == g_store.end()) return nullptr;
  it->second->last_use.store(++g_clock, std::memory_order_relaxed);
  return it->second;
}

// x = A^{-1} b (trans: A^{-T} b); w: workspace of n (b and x may be one buffer).
static void TriangularSolve(const Factors& f, bool trans, const double* b, double* x, double* w) {
  const int64_t n = f.n;
  if (!trans) {
    for (int64_t i = 0; i < n; ++i) w[f.pr[i]] = b[i];             // w = P_r b
    for (int64_t j = 0; j < n; ++j) {                               // L z = w (columns: scatter)
      const double wj = w[j];
      if (wj == 0.0) continue;
      for (int64_t p = f.lp[j]; p < f.lp[j + 1]; ++p) w[f.li[p]] -= f.lx[p] * wj;
    }
    for (int64_t j = n - 1; j >= 0; --j) {                          // U y = z
      const double wj = (w[j] /= f.ud[j]);
      if (wj == 0.0) continue;
      for (int64_t p = f.up[j]; p < f.up[j + 1]; ++p) w[f.ui[p]] -= f.ux[p] * wj;
    }
    for (int64_t i = 0; i < n; ++i) x[i] = w[f.pc[i]];              // x = P_c y
  } else {
    for (int64_t i = 0; i < n; ++i) w[f.pc[i]] = b[i];              // w = P_c^T b
    for (int64_t j = 0; j < n; ++j) {                               // U^T s = w (columns of U: gather)
      double s = w[j];
      for (int64_t p = f.up[j]; p < f.up[j + 1]; ++p) s -= f.ux[p] * w[f.ui[p]];
      w[j] = s / f.ud[j];
    }
    for (int64_t j = n - 1; j >= 0; --j) {                          // L^T t = s
      double s = w[j];
      for (int64_t p = f.lp[j]; p < f.lp[j + 1]; ++p) s -= f.lx[p] * w[f.li[p]];
      w[j] = s;
    }
    for (int64_t i = 0; i < n; ++i) x[i] = w[f.pr[i]];              // x = P_r^T t
  }
}

// Factor: `retain` (how many factorizations the pattern's store keeps alive, at least)
// travels to Python in the token slot, which a factorization does not use.
static ffi::Error Factor(int64_t key, int64_t retain, ffi::Buffer<ffi::F64> data, ffi::ResultBufferR0<ffi::S64> token) {
  return CallPython(0, key, retain, data.typed_data(), data.size_bytes(), token->typed_data(), sizeof(int64_t));
}

static ffi::Error Solve(int64_t key, int64_t trans, ffi::BufferR0<ffi::S64> token, ffi::Buffer<ffi::F64> b,
                        ffi::ResultBuffer<ffi::F64> x) {
  const int64_t t = *token.typed_data();
  if (t < 0) {  // a singular matrix: NaN, which the Newton loop treats as a failed step
    std::fill(x->typed_data(), x->typed_data() + x->element_count(), std::numeric_limits<double>::quiet_NaN());
    return ffi::Error::Success();
  }
  std::shared_ptr<const Factors> f = Lookup(key, t);
  if (f != nullptr && static_cast<int64_t>(b.element_count()) == f->n) {
    std::vector<double> w(f->n);
    TriangularSolve(*f, trans != 0, b.typed_data(), x->typed_data(), w.data());
    return ffi::Error::Success();
  }
  return CallPython(trans ? 2 : 1, key, t, b.typed_data(), b.size_bytes(), x->typed_data(), x->size_bytes());
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

// A contiguous buffer of `count` items of `itemsize` bytes, copied into `out`.
template <typename T>
static bool CopyBuffer(PyObject* obj, Py_ssize_t count, std::vector<T>* out, const char* name) {
  Py_buffer view;
  if (PyObject_GetBuffer(obj, &view, PyBUF_C_CONTIGUOUS) != 0) return false;
  bool ok = view.len == count * static_cast<Py_ssize_t>(sizeof(T));
  if (ok) {
    out->resize(count);
    std::memcpy(out->data(), view.buf, view.len);
  } else {
    PyErr_Format(PyExc_ValueError, "publish: %s has %zd bytes, expected %zd", name, view.len,
                 count * static_cast<Py_ssize_t>(sizeof(T)));
  }
  PyBuffer_Release(&view);
  return ok;
}

static PyObject* publish(PyObject*, PyObject* args) {
  long long key, token, n;
  PyObject *lp, *li, *lx, *up, *ui, *ux, *ud, *pr, *pc;
  if (!PyArg_ParseTuple(args, "LLLOOOOOOOOO", &key, &token, &n, &lp, &li, &lx, &up, &ui, &ux, &ud, &pr, &pc))
    return nullptr;
  auto f = std::make_shared<Factors>();
  f->n = n;
  if (!CopyBuffer(lp, n + 1, &f->lp, "lp") || !CopyBuffer(up, n + 1, &f->up, "up")) return nullptr;
  const Py_ssize_t lnnz = static_cast<Py_ssize_t>(f->lp[n]), unnz = static_cast<Py_ssize_t>(f->up[n]);
  if (!CopyBuffer(li, lnnz, &f->li, "li") || !CopyBuffer(lx, lnnz, &f->lx, "lx") ||
      !CopyBuffer(ui, unnz, &f->ui, "ui") || !CopyBuffer(ux, unnz, &f->ux, "ux") ||
      !CopyBuffer(ud, n, &f->ud, "ud") || !CopyBuffer(pr, n, &f->pr, "pr") || !CopyBuffer(pc, n, &f->pc, "pc"))
    return nullptr;
  std::lock_guard<std::mutex> lock(g_mutex);
  f->last_use.store(++g_clock, std::memory_order_relaxed);
  g_store[{key, token}] = std::move(f);
  Py_RETURN_NONE;
}

// last_use(key, token) -> int: when the factorization was last published or solved with
// (a clock shared by all; larger is later), -1 where it is not published.
static PyObject* last_use(PyObject*, PyObject* args) {
  long long key, token;
  if (!PyArg_ParseTuple(args, "LL", &key, &token)) return nullptr;
  std::lock_guard<std::mutex> lock(g_mutex);
  auto it = g_store.find({key, token});
  if (it == g_store.end()) return PyLong_FromLongLong(-1);
  return PyLong_FromUnsignedLongLong(it->second->last_use.load(std::memory_order_relaxed));
}

static PyObject* retract(PyObject*, PyObject* args) {
  long long key, token;
  if (!PyArg_ParseTuple(args, "LL", &key, &token)) return nullptr;
  std::shared_ptr<const Factors> gone;  // freed outside the lock
  {
    std::lock_guard<std::mutex> lock(g_mutex);
    auto it = g_store.find({key, token});
    if (it != g_store.end()) {
      gone = std::move(it->second);
      g_store.erase(it);
    }
  }
  Py_RETURN_NONE;
}

// solve(key, token, b, x, trans) -> bool: x = A^{-1} b (A^{-T} b) where the factorization is
// published (False where it is not); b and x float64 buffers of n, x writable.
static PyObject* solve(PyObject*, PyObject* args) {
  long long key, token;
  int trans;
  Py_buffer b, x;
  if (!PyArg_ParseTuple(args, "LLy*w*p", &key, &token, &b, &x, &trans)) return nullptr;
  std::shared_ptr<const Factors> f = Lookup(key, token);
  PyObject* result = Py_False;
  if (f != nullptr) {
    const Py_ssize_t bytes = f->n * static_cast<Py_ssize_t>(sizeof(double));
    if (b.len != bytes || x.len != bytes) {
      PyErr_Format(PyExc_ValueError, "solve: b and x need %zd bytes, got %zd and %zd", bytes, b.len, x.len);
      result = nullptr;
    } else {
      std::vector<double> w(f->n);
      Py_BEGIN_ALLOW_THREADS
      TriangularSolve(*f, trans != 0, static_cast<const double*>(b.buf), static_cast<double*>(x.buf), w.data());
      Py_END_ALLOW_THREADS
      result = Py_True;
    }
  }
  PyBuffer_Release(&b);
  PyBuffer_Release(&x);
  Py_XINCREF(result);
  return result;
}

static PyObject* capsule(void* fn) { return PyCapsule_New(fn, nullptr, nullptr); }
static PyObject* factor_target(PyObject*, PyObject*) { return capsule(reinterpret_cast<void*>(JaxviscoLuFactor)); }
static PyObject* solve_target(PyObject*, PyObject*) { return capsule(reinterpret_cast<void*>(JaxviscoLuSolve)); }

static PyMethodDef kMethods[] = {
    {"set_callable", set_callable, METH_O, "Register the Python callable that does the host LU work."},
    {"publish", publish, METH_VARARGS,
     "publish(key, token, n, lp, li, lx, up, ui, ux, ud, perm_r, perm_c): keep triangular factors for C++ solves."},
    {"last_use", last_use, METH_VARARGS, "last_use(key, token) -> int: clock of its latest use, -1 if absent."},
    {"retract", retract, METH_VARARGS, "retract(key, token): forget a published factorization."},
    {"solve", solve, METH_VARARGS, "solve(key, token, b, x, trans) -> bool: solve with a published factorization."},
    {"factor_target", factor_target, METH_NOARGS, "Capsule of the jaxvisco_lu_factor FFI handler."},
    {"solve_target", solve_target, METH_NOARGS, "Capsule of the jaxvisco_lu_solve FFI handler."},
    {nullptr, nullptr, 0, nullptr}};

static struct PyModuleDef kModule = {PyModuleDef_HEAD_INIT, "_hostlu", "jaxvisco's host sparse LU as XLA FFI targets",
                                     -1, kMethods};

PyMODINIT_FUNC PyInit__hostlu(void) { return PyModule_Create(&kModule); }
