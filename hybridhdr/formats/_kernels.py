"""Numba kernels for the Prophesee RAW (EVT 2.0, 2.1, 3.0) and DAT codecs.

Every kernel takes contiguous 1-D arrays and scalars, does no I/O and never raises: decoders
return ``(next_word, n_events, n_triggers, error_code, error_word)`` and keep their decoding
state (time high, loop count, current row, vector base ...) in a small int64 array ``st`` that
the caller passes back on the next call, so a file can be decoded block by block.

Output events are written into ``out``, an int64 view of an ``EVENT_DTYPE`` array (16-byte
records: ``t`` int64 at byte 0; ``x`` uint16 at 8, ``y`` uint16 at 10, ``p`` int8 at 12, three
zero padding bytes). Record ``k`` is ``out[2k] = t`` (µs) and
``out[2k+1] = x | y << 16 | (p & 0xFF) << 32``, one 16-byte store per event on a little-endian
host. Triggers go to three separate arrays ``trig_t`` (int64 µs), ``trig_ch`` (uint16) and
``trig_edge`` (int8, ±1).

Time-order policy (shared by all decoders): ``tmax`` is the latest event time decoded so far. An
event earlier than ``tmax - window_us`` is an error (:data:`ERR_BACKWARDS`); an event earlier than
``tmax`` but within the window only increments the out-of-order counter, and the caller re-sorts.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

# Error codes returned by the decoders.
ERR_NONE = 0
ERR_X_RANGE = 1  #: x >= sensor width; st[ST_ERR_A] = x, st[ST_ERR_B] = width
ERR_Y_RANGE = 2  #: y >= sensor height; st[ST_ERR_A] = y, st[ST_ERR_B] = height
ERR_BACKWARDS = 3  #: t < tmax - window; st[ST_ERR_A] = t, st[ST_ERR_B] = tmax
ERR_WORD_TYPE = 4  #: unused word type; st[ST_ERR_A] = type, st[ST_ERR_B] = word

# Shared state slots (each decoder has its own layout for the slots below ST_TMAX).
ST_TMAX = 8  #: latest event time (µs), -1 before the first event
ST_DISORDER = 9  #: number of events decoded earlier than the latest one (within the window)
ST_ERR_A = 10
ST_ERR_B = 11
ST_SIZE = 16

# EVT 2.0 / 2.1 slots
E2_STARTED = 0
E2_LAST_TH = 1
E2_LOOPS = 2
E2_BASE = 3
# EVT 3.0 slots
E3_STARTED = 0
E3_LAST_TH = 1
E3_LOOPS = 2
E3_BASE = 3
E3_T = 4
E3_Y = 5
E3_BX = 6
E3_VP = 7
# DAT slots
DAT_HAVE_PREV = 0
DAT_PREV_RAW = 1
DAT_PREV_T = 2

#: EVT 2.0 TIME_HIGH loop rule: a drop of at least 0xFFFFFFF - 10 (i.e. (2^34-1 - (10 << 6)) µs)
EVT2_LOOP_DROP = 0xFFFFFFF - 10
#: EVT 3.0 TIME_HIGH loop rule: a drop of at least 0xFFF - 10 (i.e. (0xFFF << 12) - (10 << 12) µs)
EVT3_LOOP_DROP = 0xFFF - 10


def new_state() -> np.ndarray:
    """A fresh decoder state (int64 array of length :data:`ST_SIZE`)."""
    st = np.zeros(ST_SIZE, np.int64)
    st[ST_TMAX] = -1
    st[E3_Y] = -1
    st[E3_BX] = -1
    return st


#: De Bruijn table: index of the lowest set bit of a 32-bit value v is
#: _DEBRUIJN32[((v & -v) * 0x077CB531 >> 27) & 31]
_DEBRUIJN32 = np.array([0, 1, 28, 2, 29, 14, 24, 3, 30, 22, 20, 15, 25, 17, 4, 8,
                        31, 27, 13, 23, 21, 19, 16, 7, 26, 12, 18, 6, 11, 5, 10, 9], np.int64)


@njit(cache=True, nogil=True, inline="always")
def _pack_xyp(x, y, pbyte):
    return np.int64(x) | (np.int64(y) << 16) | (np.int64(pbyte) << 32)


# ---------------------------------------------------------------------------------------------
# EVT 2.0
# ---------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def evt2_decode(words, start, out, n, cap, trig_t, trig_ch, trig_edge, nt, tcap, st, width, height,
                window_us, strict):
    """Decode EVT 2.0 32-bit words ``words[start:]``.

    Parameters
    ----------
    words : ndarray of shape (W,), uint32
        Little-endian EVT 2.0 words.
    start : int
        First word to decode.
    out : ndarray of shape (2 * cap,), int64
        Packed event records (see the module docstring); ``n`` are already filled.
    cap : int
        Capacity of ``out`` in events. Decoding stops before a word when ``n == cap``.
    trig_t, trig_ch, trig_edge : ndarray of shape (tcap,)
        Trigger outputs (µs, channel, ±1); ``nt`` are filled. Decoding stops when full.
    st : ndarray of shape (16,), int64
        Decoder state, updated in place.
    width, height : int
        Sensor size in pixels; coordinates must be below them.
    window_us : int
        Reorder window in µs (see the module docstring).
    strict : bool
        Whether unused word types (0x2-0x7, 0x9, 0xB, 0xC) are errors (else skipped).

    Returns
    -------
    next_word, n, nt, err, err_word : int
        Where decoding stopped, the new counts, an error code (0 = none) and the offending word.
    """
    started = st[E2_STARTED]
    last_th = st[E2_LAST_TH]
    loops = st[E2_LOOPS]
    base = st[E2_BASE]
    tmax = st[ST_TMAX]
    disorder = st[ST_DISORDER]
    nw = words.shape[0]
    i = start
    err = 0
    while i < nw:
        if n >= cap or nt >= tcap:
            break
        w = np.int64(words[i])
        typ = w >> 28
        if typ <= 1:
            if started:
                t = base | ((w >> 22) & 63)
                x = (w >> 11) & 0x7FF
                y = w & 0x7FF
                if x >= width:
                    err = ERR_X_RANGE
                    st[ST_ERR_A] = x
                    st[ST_ERR_B] = width
                    break
                if y >= height:
                    err = ERR_Y_RANGE
                    st[ST_ERR_A] = y
                    st[ST_ERR_B] = height
                    break
                if t >= tmax:
                    tmax = t
                else:
                    if t < tmax - window_us:
                        err = ERR_BACKWARDS
                        st[ST_ERR_A] = t
                        st[ST_ERR_B] = tmax
                        break
                    disorder += 1
                out[2 * n] = t
                out[2 * n + 1] = _pack_xyp(x, y, 1 if typ == 1 else 0xFF)
                n += 1
        elif typ == 8:
            th = w & 0xFFFFFFF
            if started:
                if last_th - th >= EVT2_LOOP_DROP:
                    loops += 1
            started = 1
            last_th = th
            base = (loops << 34) | (th << 6)
        elif typ == 0xA:
            if started:
                trig_t[nt] = base | ((w >> 22) & 63)
                trig_ch[nt] = (w >> 8) & 0x1F
                trig_edge[nt] = 1 if (w & 1) else -1
                nt += 1
        elif typ >= 0xD:
            pass  # IMU, OTHERS, CONTINUED
        elif strict:
            err = ERR_WORD_TYPE
            st[ST_ERR_A] = typ
            st[ST_ERR_B] = w
            break
        i += 1
    st[E2_STARTED] = started
    st[E2_LAST_TH] = last_th
    st[E2_LOOPS] = loops
    st[E2_BASE] = base
    st[ST_TMAX] = tmax
    st[ST_DISORDER] = disorder
    return i, n, nt, err, i


# ---------------------------------------------------------------------------------------------
# EVT 2.1
# ---------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def evt21_decode(words, start, out, n, cap, trig_t, trig_ch, trig_edge, nt, tcap, st, width, height,
                 window_us, strict, legacy):
    """Decode EVT 2.1 64-bit words given as pairs of uint32 (``words[2k], words[2k+1]``).

    ``start`` and the returned ``next_word`` count 64-bit words. With ``legacy`` false (standard
    order) the mask is the first uint32 and the header the second; with ``legacy`` true the header
    comes first. Decoding stops before a word when fewer than 32 output slots remain. Other
    parameters and the return value are as in :func:`evt2_decode`.
    """
    started = st[E2_STARTED]
    last_th = st[E2_LAST_TH]
    loops = st[E2_LOOPS]
    base = st[E2_BASE]
    tmax = st[ST_TMAX]
    disorder = st[ST_DISORDER]
    hoff = 0 if legacy else 1
    moff = 1 - hoff
    nw = words.shape[0] // 2
    i = start
    err = 0
    while i < nw:
        if n + 32 > cap or nt >= tcap:
            break
        h = np.int64(words[2 * i + hoff])
        typ = h >> 28
        if typ <= 1:
            if started:
                m = np.int64(words[2 * i + moff])
                if m != 0:
                    t = base | ((h >> 22) & 63)
                    x0 = (h >> 11) & 0x7FF
                    y = h & 0x7FF
                    if y >= height:
                        err = ERR_Y_RANGE
                        st[ST_ERR_A] = y
                        st[ST_ERR_B] = height
                        break
                    if t >= tmax:
                        tmax = t
                    else:
                        if t < tmax - window_us:
                            err = ERR_BACKWARDS
                            st[ST_ERR_A] = t
                            st[ST_ERR_B] = tmax
                            break
                        disorder += 1
                    yp = (np.int64(y) << 16) | (np.int64(1 if typ == 1 else 0xFF) << 32)
                    while m != 0:
                        low = m & (-m)
                        x = x0 + _DEBRUIJN32[((low * 0x077CB531) >> 27) & 31]
                        m ^= low
                        if x >= width:
                            err = ERR_X_RANGE
                            st[ST_ERR_A] = x
                            st[ST_ERR_B] = width
                            break
                        out[2 * n] = t
                        out[2 * n + 1] = yp | x
                        n += 1
                    if err:
                        break
        elif typ == 8:
            th = h & 0xFFFFFFF
            if started:
                if last_th - th >= EVT2_LOOP_DROP:
                    loops += 1
            started = 1
            last_th = th
            base = (loops << 34) | (th << 6)
        elif typ == 0xA:
            if started:
                trig_t[nt] = base | ((h >> 22) & 63)
                trig_ch[nt] = (h >> 8) & 0x1F
                trig_edge[nt] = 1 if (h & 1) else -1
                nt += 1
        elif typ >= 0xD:
            pass
        elif strict:
            err = ERR_WORD_TYPE
            st[ST_ERR_A] = typ
            st[ST_ERR_B] = h
            break
        i += 1
    st[E2_STARTED] = started
    st[E2_LAST_TH] = last_th
    st[E2_LOOPS] = loops
    st[E2_BASE] = base
    st[ST_TMAX] = tmax
    st[ST_DISORDER] = disorder
    return i, n, nt, err, i


# ---------------------------------------------------------------------------------------------
# EVT 3.0
# ---------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def evt3_decode(words, start, out, n, cap, trig_t, trig_ch, trig_edge, nt, tcap, st, width, height,
                window_us, strict):
    """Decode EVT 3.0 16-bit words ``words[start:]`` (uint16, little-endian).

    Words before the first TIME_HIGH are skipped; events before the first ADDR_Y (and vectors
    before the first VECT_BASE_X) after it are dropped, since their row (column) is unknown. A
    TIME_HIGH resets the low 12 time bits to 0 until the next TIME_LOW. Decoding stops before a
    word when fewer than 12 output slots remain. Parameters and return value as in
    :func:`evt2_decode`; ``strict`` makes the unused types 0x1, 0x9, 0xB and 0xC errors.
    """
    started = st[E3_STARTED]
    last_th = st[E3_LAST_TH]
    loops = st[E3_LOOPS]
    base = st[E3_BASE]
    t = st[E3_T]
    y = st[E3_Y]
    bx = st[E3_BX]
    vp = st[E3_VP]
    tmax = st[ST_TMAX]
    disorder = st[ST_DISORDER]
    nw = words.shape[0]
    i = start
    err = 0
    if not started:
        while i < nw:
            w = np.int64(words[i])
            i += 1
            if (w >> 12) == 8:
                started = 1
                last_th = w & 0xFFF
                base = (loops << 24) | (last_th << 12)
                t = base
                break
    while i < nw:
        if n + 12 > cap or nt >= tcap:
            break
        w = np.int64(words[i])
        typ = w >> 12
        if typ == 2:  # EVT_ADDR_X
            if y >= 0:
                x = w & 0x7FF
                if x >= width:
                    err = ERR_X_RANGE
                    st[ST_ERR_A] = x
                    st[ST_ERR_B] = width
                    break
                if y >= height:
                    err = ERR_Y_RANGE
                    st[ST_ERR_A] = y
                    st[ST_ERR_B] = height
                    break
                if t >= tmax:
                    tmax = t
                else:
                    if t < tmax - window_us:
                        err = ERR_BACKWARDS
                        st[ST_ERR_A] = t
                        st[ST_ERR_B] = tmax
                        break
                    disorder += 1
                out[2 * n] = t
                out[2 * n + 1] = _pack_xyp(x, y, 1 if (w & 0x800) else 0xFF)
                n += 1
        elif typ == 0:  # EVT_ADDR_Y
            y = w & 0x7FF
        elif typ == 6:  # EVT_TIME_LOW
            t = base | (w & 0xFFF)
        elif typ == 4 or typ == 5:  # VECT_12 / VECT_8
            nb = 12 if typ == 4 else 8
            if bx >= 0:
                m = w & (0xFFF if typ == 4 else 0xFF)
                if m != 0 and y >= 0:
                    if y >= height:
                        err = ERR_Y_RANGE
                        st[ST_ERR_A] = y
                        st[ST_ERR_B] = height
                        break
                    if t >= tmax:
                        tmax = t
                    else:
                        if t < tmax - window_us:
                            err = ERR_BACKWARDS
                            st[ST_ERR_A] = t
                            st[ST_ERR_B] = tmax
                            break
                        disorder += 1
                    yp = (np.int64(y) << 16) | (np.int64(1 if vp else 0xFF) << 32)
                    if bx + nb <= width:
                        # branch-free: write all nb slots, advance n by the valid bits only
                        for b in range(nb):
                            out[2 * n] = t
                            out[2 * n + 1] = yp | (bx + b)
                            n += (m >> b) & 1
                    else:
                        for b in range(nb):
                            if (m >> b) & 1:
                                x = bx + b
                                if x >= width:
                                    err = ERR_X_RANGE
                                    st[ST_ERR_A] = x
                                    st[ST_ERR_B] = width
                                    break
                                out[2 * n] = t
                                out[2 * n + 1] = yp | x
                                n += 1
                        if err:
                            break
                bx += nb
        elif typ == 3:  # VECT_BASE_X
            bx = w & 0x7FF
            vp = (w >> 11) & 1
        elif typ == 8:  # EVT_TIME_HIGH
            th = w & 0xFFF
            if last_th - th >= EVT3_LOOP_DROP:
                loops += 1
            last_th = th
            base = (loops << 24) | (th << 12)
            t = base
        elif typ == 0xA:  # EXT_TRIGGER
            trig_t[nt] = t
            trig_ch[nt] = (w >> 8) & 0xF
            trig_edge[nt] = 1 if (w & 1) else -1
            nt += 1
        elif typ == 7 or typ >= 0xD:
            pass  # CONTINUED_4, IMU, OTHERS, CONTINUED_12
        elif strict:
            err = ERR_WORD_TYPE
            st[ST_ERR_A] = typ
            st[ST_ERR_B] = w
            break
        i += 1
    st[E3_STARTED] = started
    st[E3_LAST_TH] = last_th
    st[E3_LOOPS] = loops
    st[E3_BASE] = base
    st[E3_T] = t
    st[E3_Y] = y
    st[E3_BX] = bx
    st[E3_VP] = vp
    st[ST_TMAX] = tmax
    st[ST_DISORDER] = disorder
    return i, n, nt, err, i


# ---------------------------------------------------------------------------------------------
# Counting (upper bounds used to size the output of a whole-file read)
# ---------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def evt3_count(words):
    """Upper bound of the events in EVT 3.0 ``words``: ADDR_X words plus VECT_12/VECT_8 bits."""
    c = 0
    for i in range(words.shape[0]):
        w = np.int64(words[i])
        typ = w >> 12
        if typ == 2:
            c += 1
        elif typ == 4:
            m = w & 0xFFF
            while m:
                m &= m - 1
                c += 1
        elif typ == 5:
            m = w & 0xFF
            while m:
                m &= m - 1
                c += 1
    return c


@njit(cache=True, nogil=True)
def evt21_count(words, legacy):
    """Upper bound of the events in EVT 2.1 ``words`` (uint32 pairs): set mask bits of CD words."""
    hoff = 0 if legacy else 1
    c = 0
    for i in range(words.shape[0] // 2):
        h = np.int64(words[2 * i + hoff])
        if (h >> 28) <= 1:
            m = np.int64(words[2 * i + 1 - hoff])
            while m:
                m &= m - 1
                c += 1
    return c


# ---------------------------------------------------------------------------------------------
# DAT
# ---------------------------------------------------------------------------------------------
# Time rule: t_0 = raw_0 and t_i = t_{i-1} + d_i with d_i = raw_i - raw_{i-1} read as a signed
# 32-bit number, so the 32-bit counter (wrapping every 2^32 µs, 71.6 min) is unwrapped exactly as
# long as consecutive records differ by less than 2^31 µs. Being a prefix sum, it parallelises.

@njit(cache=True, nogil=True, inline="always")
def _sdiff32(a, b):
    d = (a - b) & 0xFFFFFFFF
    if d >= 0x80000000:
        d -= 0x100000000
    return d


@njit(cache=True, nogil=True)
def _dat_segment_scan(words, a, b, prev_raw):
    """Sum and maximum of the running time offset over records [a, b) (relative to t_{a-1})."""
    rel = np.int64(0)
    mx = np.int64(-(1 << 62))
    pr = prev_raw
    for i in range(a, b):
        raw = np.int64(words[2 * i])
        rel += _sdiff32(raw, pr)
        pr = raw
        if rel > mx:
            mx = rel
    return rel, mx


@njit(cache=True, nogil=True)
def _dat_segment_decode(words, a, b, prev_raw, t0, tmax, out, width, height, window_us, res):
    """Decode records [a, b) starting from t_{a-1} = t0; res = [err, err_rec, err_a, err_b, disorder]."""
    pr = prev_raw
    t = t0
    disorder = 0
    for i in range(a, b):
        raw = np.int64(words[2 * i])
        d = np.int64(words[2 * i + 1])
        t += _sdiff32(raw, pr)
        pr = raw
        x = d & 0x3FFF
        y = (d >> 14) & 0x3FFF
        if x >= width:
            res[0] = ERR_X_RANGE
            res[1] = i
            res[2] = x
            res[3] = width
            break
        if y >= height:
            res[0] = ERR_Y_RANGE
            res[1] = i
            res[2] = y
            res[3] = height
            break
        if t >= tmax:
            tmax = t
        else:
            if t < tmax - window_us:
                res[0] = ERR_BACKWARDS
                res[1] = i
                res[2] = t
                res[3] = tmax
                break
            disorder += 1
        out[2 * i] = t
        out[2 * i + 1] = _pack_xyp(x, y, 1 if (d >> 28) & 1 else 0xFF)
    res[4] = disorder
    return t, tmax


@njit(cache=True, nogil=True)
def dat_decode(words, out, st, width, height, window_us):
    """Decode DAT CD records serially.

    Parameters
    ----------
    words : ndarray of shape (2 * R,), uint32
        R records: ``words[2r]`` the 32-bit time (µs), ``words[2r+1]`` x ``[13:0]``, y ``[27:14]``,
        polarity ``[28]``.
    out : ndarray of shape (2 * R,), int64
        Packed event records (module docstring), one per input record.
    st : ndarray of shape (16,), int64
        Decoder state, updated in place.

    Returns
    -------
    n, err, err_record : int
        Number of records decoded (R unless an error stopped it), error code, offending record.
    """
    nrec = words.shape[0] // 2
    if nrec == 0:
        return 0, 0, 0
    if st[DAT_HAVE_PREV]:
        prev_raw = st[DAT_PREV_RAW]
        prev_t = st[DAT_PREV_T]
    else:
        prev_raw = np.int64(words[0])
        prev_t = prev_raw
    res = np.zeros(5, np.int64)
    t, tmax = _dat_segment_decode(words, 0, nrec, prev_raw, prev_t, st[ST_TMAX], out, width, height,
                                  window_us, res)
    st[ST_DISORDER] += res[4]
    if res[0] != 0:
        st[ST_ERR_A] = res[2]
        st[ST_ERR_B] = res[3]
        return res[1], res[0], res[1]
    st[DAT_HAVE_PREV] = 1
    st[DAT_PREV_RAW] = np.int64(words[2 * nrec - 2])
    st[DAT_PREV_T] = t
    st[ST_TMAX] = tmax
    return nrec, 0, 0


@njit(cache=True, nogil=True, parallel=True)
def dat_decode_parallel(words, out, st, width, height, window_us, nseg):
    """Two-pass parallel version of :func:`dat_decode` with identical output and errors.

    Pass 1 computes, per segment of records, the sum and running maximum of the signed time
    steps; a prefix over segments gives each segment's start time and the latest earlier time;
    pass 2 decodes the segments independently. ``nseg`` is the number of segments (>= 1).
    """
    nrec = words.shape[0] // 2
    if nrec == 0:
        return 0, 0, 0
    nseg = max(1, min(nseg, nrec))
    if st[DAT_HAVE_PREV]:
        prev_raw0 = st[DAT_PREV_RAW]
        prev_t0 = st[DAT_PREV_T]
    else:
        prev_raw0 = np.int64(words[0])
        prev_t0 = prev_raw0
    bounds = np.empty(nseg + 1, np.int64)
    for s in range(nseg + 1):
        bounds[s] = (nrec * s) // nseg
    sums = np.empty(nseg, np.int64)
    maxs = np.empty(nseg, np.int64)
    for s in prange(nseg):
        a = bounds[s]
        pr = prev_raw0 if a == 0 else np.int64(words[2 * a - 2])
        sums[s], maxs[s] = _dat_segment_scan(words, a, bounds[s + 1], pr)
    starts = np.empty(nseg, np.int64)
    tmaxs = np.empty(nseg, np.int64)
    t = prev_t0
    tm = st[ST_TMAX]
    for s in range(nseg):
        starts[s] = t
        tmaxs[s] = tm
        if bounds[s + 1] > bounds[s]:
            tm = max(tm, t + maxs[s])
        t += sums[s]
    res = np.zeros((nseg, 5), np.int64)
    for s in prange(nseg):
        a = bounds[s]
        pr = prev_raw0 if a == 0 else np.int64(words[2 * a - 2])
        _dat_segment_decode(words, a, bounds[s + 1], pr, starts[s], tmaxs[s], out, width, height,
                            window_us, res[s])
    disorder = 0
    for s in range(nseg):
        disorder += res[s, 4]
        if res[s, 0] != 0:
            st[ST_DISORDER] += disorder
            st[ST_ERR_A] = res[s, 2]
            st[ST_ERR_B] = res[s, 3]
            return res[s, 1], res[s, 0], res[s, 1]
    st[ST_DISORDER] += disorder
    st[DAT_HAVE_PREV] = 1
    st[DAT_PREV_RAW] = np.int64(words[2 * nrec - 2])
    st[DAT_PREV_T] = t
    st[ST_TMAX] = tm
    return nrec, 0, 0


# ---------------------------------------------------------------------------------------------
# Encoders
# ---------------------------------------------------------------------------------------------
# Encoder state: es[0] = current absolute time-high index (-1 before the first), es[1] = current
# low bits (EVT3 TIME_LOW, -1 = unknown), es[2] = current y (EVT3, -1 = unknown).

@njit(cache=True, nogil=True)
def evt2_encode(t, x, y, p, tt, tch, te, es, out):
    """Encode sorted events and triggers (merged by time, triggers first on ties) as EVT 2.0.

    Parameters
    ----------
    t, x, y, p : ndarray of shape (N,)
        Event columns: int64 µs (>= 0, non-decreasing), uint16, uint16, int8 (±1).
    tt, tch, te : ndarray of shape (M,)
        Trigger columns: int64 µs (non-decreasing, >= the last written time), uint16 channel
        (< 32), int8 edge.
    es : ndarray of shape (4,), int64
        Encoder state (updated).
    out : ndarray of shape (>= N + M + 2 * (loops crossed) + 2 * (N + M),), uint32
        Output words.

    Returns
    -------
    n_words : int

    Notes
    -----
    A TIME_HIGH word is written whenever t >> 6 changes. When the time crosses a 2^34 µs loop
    boundary, TIME_HIGH words 0xFFFFFFF then 0 are written for each loop crossed so that a reader
    applying the loop rule (drop >= 0xFFFFFFF - 10) counts every loop, whatever the gap.
    """
    nw = 0
    cur = es[0]
    ne = t.shape[0]
    ntr = tt.shape[0]
    i = 0
    k = 0
    while i < ne or k < ntr:
        is_trig = k < ntr and (i >= ne or tt[k] <= t[i])
        ti = tt[k] if is_trig else t[i]
        hi = ti >> 6
        if hi != cur:
            if cur < 0:
                loop_c = np.int64(0)
                raw_c = np.int64(-1)
            else:
                loop_c = cur >> 28
                raw_c = cur & 0xFFFFFFF
            loop_t = hi >> 28
            while loop_c < loop_t:
                if raw_c != 0xFFFFFFF:
                    out[nw] = np.uint32((8 << 28) | 0xFFFFFFF)
                    nw += 1
                out[nw] = np.uint32(8 << 28)
                nw += 1
                loop_c += 1
                raw_c = 0
            out[nw] = np.uint32((8 << 28) | (hi & 0xFFFFFFF))
            nw += 1
            cur = hi
        if is_trig:
            out[nw] = np.uint32((0xA << 28) | ((ti & 63) << 22) | (np.int64(tch[k]) << 8)
                                | (1 if te[k] > 0 else 0))
            k += 1
        else:
            out[nw] = np.uint32(((1 if p[i] > 0 else 0) << 28) | ((ti & 63) << 22)
                                | (np.int64(x[i]) << 11) | np.int64(y[i]))
            i += 1
        nw += 1
    es[0] = cur
    return nw


@njit(cache=True, nogil=True, inline="always")
def _evt3_time(ti, es, out, nw):
    hi = ti >> 12
    cur = es[0]
    if hi != cur:
        if cur < 0:
            loop_c = np.int64(0)
            raw_c = np.int64(-1)
        else:
            loop_c = cur >> 12
            raw_c = cur & 0xFFF
        loop_t = hi >> 12
        while loop_c < loop_t:
            if raw_c != 0xFFF:
                out[nw] = 0x8FFF
                nw += 1
            out[nw] = 0x8000
            nw += 1
            loop_c += 1
            raw_c = 0
        out[nw] = np.uint16(0x8000 | (hi & 0xFFF))
        nw += 1
        es[0] = hi
        es[1] = -1
    lo = ti & 0xFFF
    if lo != es[1]:
        out[nw] = np.uint16(0x6000 | lo)
        nw += 1
        es[1] = lo
    return nw


@njit(cache=True, nogil=True)
def evt3_encode(t, x, y, p, tt, tch, te, es, out, use_vectors):
    """Encode sorted events and triggers (merged by time, triggers first on ties) as EVT 3.0.

    Parameters
    ----------
    t, x, y, p, tt, tch, te, es
        As in :func:`evt2_encode`; trigger channels must be < 16.
    out : ndarray, uint16
        Output words; ``4 * (N + M) + 2 * (loops crossed) + 8`` is always enough.
    use_vectors : bool
        Whether to encode runs as VECT_BASE_X + VECT_12 / VECT_8.

    Returns
    -------
    n_words : int

    Notes
    -----
    TIME_HIGH is written when t >> 12 changes (with 0xFFF, 0 pairs for every 2^24 µs loop crossed,
    as in :func:`evt2_encode`), always followed by a TIME_LOW. ADDR_Y is written when y changes.
    Consecutive events with equal t, y and p and strictly increasing x are written as vectors
    when at least three of them fall within 12 columns of the first (VECT_8 if within 8);
    vectors continue (without a new VECT_BASE_X) while the next such events lie within the next
    12 columns. Everything else is an ADDR_X. Event order is preserved exactly.
    """
    nw = 0
    ne = t.shape[0]
    ntr = tt.shape[0]
    i = 0
    k = 0
    while i < ne or k < ntr:
        if k < ntr and (i >= ne or tt[k] <= t[i]):
            nw = _evt3_time(tt[k], es, out, nw)
            out[nw] = np.uint16(0xA000 | (np.int64(tch[k]) << 8) | (1 if te[k] > 0 else 0))
            nw += 1
            k += 1
            continue
        ti = t[i]
        nw = _evt3_time(ti, es, out, nw)
        yi = np.int64(y[i])
        if yi != es[2]:
            out[nw] = np.uint16(yi)
            nw += 1
            es[2] = yi
        pi = p[i]
        x0 = np.int64(x[i])
        # length of the run starting at i that fits in [x0, x0 + 12)
        j = i + 1
        if use_vectors:
            while (j < ne and t[j] == ti and np.int64(y[j]) == yi and p[j] == pi
                   and np.int64(x[j]) > np.int64(x[j - 1]) and np.int64(x[j]) < x0 + 12):
                j += 1
        if j - i >= 3:
            pbit = 0x800 if pi > 0 else 0
            out[nw] = np.uint16(0x3000 | pbit | x0)
            nw += 1
            bx = x0
            while True:
                m = np.int64(0)
                last = np.int64(0)
                while i < j:
                    off = np.int64(x[i]) - bx
                    m |= np.int64(1) << off
                    last = off
                    i += 1
                if last < 8:
                    out[nw] = np.uint16(0x5000 | m)
                    bx += 8
                else:
                    out[nw] = np.uint16(0x4000 | m)
                    bx += 12
                nw += 1
                # continue the vector with the next events in [bx, bx + 12)?
                if not (i < ne and t[i] == ti and np.int64(y[i]) == yi and p[i] == pi
                        and np.int64(x[i]) > np.int64(x[i - 1]) and np.int64(x[i]) >= bx
                        and np.int64(x[i]) < bx + 12):
                    break
                j = i + 1
                while (j < ne and t[j] == ti and np.int64(y[j]) == yi and p[j] == pi
                       and np.int64(x[j]) > np.int64(x[j - 1]) and np.int64(x[j]) < bx + 12):
                    j += 1
        else:
            out[nw] = np.uint16(0x2000 | (0x800 if pi > 0 else 0) | x0)
            nw += 1
            i += 1
    return nw


@njit(cache=True, nogil=True)
def dat_encode(rec, prev_t, width, height, out):
    """Check and pack ``EVENT_DTYPE`` records into DAT CD words, in one pass.

    Parameters
    ----------
    rec : ndarray of shape (2N,), int64
        The records (``rec[2i] = t`` in µs, ``rec[2i+1] = x | y << 16 | p << 32`` and padding).
    prev_t : int
        Time (µs) the first record follows (its own time for the first records of a file).
    width, height : int
        Sensor size; coordinates must be below it.
    out : ndarray of shape (2N,), uint32
        DAT words: ``out[2i] = t mod 2^32``, ``out[2i+1] = x | y << 14 | (p > 0) << 28``.

    Returns
    -------
    bad, gap : int
        The index of the first record earlier than the one before it (or than ``prev_t``), with
        p not +1 or -1 or a coordinate outside the sensor (``out`` is then incomplete), else -1;
        and the largest step between consecutive times from ``prev_t`` (the writer refuses steps
        of 2^31 µs or more, which the 32-bit time cannot carry).

    Notes
    -----
    Blocks of 512 records are checked without early exit (min/max/or reductions), so the loop
    has no data-dependent branch; a block that fails is scanned again for the exact index.
    """
    n = rec.shape[0] // 2
    gap = np.int64(0)
    last = np.int64(prev_t)
    for b0 in range(0, n, 512):
        b1 = min(n, b0 + 512)
        start = last
        mind = np.int64(0)
        maxx = np.int64(0)
        maxy = np.int64(0)
        pbad = np.int64(0)
        for i in range(b0, b1):
            t = rec[2 * i]
            w = rec[2 * i + 1]
            d = t - last
            last = t
            gap = max(gap, d)
            mind = min(mind, d)
            x = w & 0xFFFF
            y = (w >> 16) & 0xFFFF
            pb = (w >> 32) & 0xFF
            maxx = max(maxx, x)
            maxy = max(maxy, y)
            pbad |= (pb + 1) & 0xFD  # 0 only for the bytes 0x01 (+1) and 0xFF (-1)
            out[2 * i] = np.uint32(t & 0xFFFFFFFF)
            out[2 * i + 1] = np.uint32(x | (y << 14) | (np.int64(pb == 1) << 28))
        if mind < 0 or maxx >= width or maxy >= height or pbad != 0:
            last = start
            for i in range(b0, b1):
                t = rec[2 * i]
                w = rec[2 * i + 1]
                pb = (w >> 32) & 0xFF
                if (t < last or (w & 0xFFFF) >= width or ((w >> 16) & 0xFFFF) >= height
                        or (pb != 1 and pb != 0xFF)):
                    return i, gap
                last = t
    return -1, gap
