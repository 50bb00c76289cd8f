// A Python object's buffer checked for the compiled modules (meshes/_sweep.cpp,
// settle/_simplex.cpp, settle/_moves.cpp): C-contiguous, of one struct format ("d", "q" or "b")
// and item size, and `writable` where asked; otherwise the buffer is not held and `error` is
// set, naming `what`.
#ifndef KNEESEAT_BUFFERS_H
#define KNEESEAT_BUFFERS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <cstring>

namespace kneeseat {

inline bool get_buffer(PyObject *obj, Py_buffer *view, const char *format, Py_ssize_t itemsize,
                       const char *what, PyObject *error = PyExc_TypeError, bool writable = false) {
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0)) < 0)
        return false;
    const char *f = view->format ? view->format : "B";
    if (*f == '<' || *f == '=' || *f == '@') ++f;
    // int64 is "q", or "l" where a long is 8 bytes
    bool ok = view->itemsize == itemsize &&
              (std::strcmp(f, format) == 0 || (itemsize == 8 && *format == 'q' && std::strcmp(f, "l") == 0));
    if (!ok) {
        PyErr_Format(error, "%s: expected a C-contiguous buffer of format '%s'", what, format);
        PyBuffer_Release(view);
    }
    return ok;
}

}  // namespace kneeseat

#endif
