"""bayespd/bond_loops.py: the compiled loops against the torch / numpy / scipy paths they
stand in for, bit for bit where they do the same operations in the same order, and the
tangent against central differences of the force."""
import threading

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components

import bayespd as bp
from bayespd import bond_loops
from bayespd.damage import DamageIndex

numba = pytest.importorskip("numba")


def plate(dim=2):
    p = bp.grid_2d(7.0, 5.0, 1.0) if dim == 2 else bp.grid_3d(4.0, 3.0, 3.0, 1.0)
    return p, bp.find_bonds(p, 2.0)


def geometry(bonds, dtype=torch.float64):
    ends = (torch.as_tensor(bonds.i, dtype=torch.int32).numpy(), torch.as_tensor(bonds.j, dtype=torch.int32).numpy())
    return ends, torch.as_tensor(bonds.xi.T.copy(), dtype=dtype), torch.as_tensor(bonds.length, dtype=dtype)


def numpy_bond(u, bonds, dtype=np.float64):
    """(y, |y|, e, eta . (y + xi)) in the kernels' order of operations, vectorised:
    eta = u_j - u_i, y = eta + xi, |y| = sqrt(sum y^2) (correctly rounded),
    e = eta . (y + xi) / (|y| + |xi|)."""
    xi, L = bonds.xi.astype(dtype), bonds.length.astype(dtype)
    eta = u[bonds.j] - u[bonds.i]
    y = eta + xi
    r = np.sqrt(sum(y[:, a] * y[:, a] for a in range(y.shape[1])))
    num = sum(eta[:, a] * (y[:, a] + xi[:, a]) for a in range(y.shape[1]))
    return y, r, num / (r + L), num


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("dim", [2, 3])
def test_stretch_is_the_reference_formula_bit_for_bit(dim, dtype):
    """s = e / |xi| with e = eta . (y + xi) / (|y| + |xi|) (= |y| - |xi| without its
    cancellation): the compiled stretch equals the same operations done by numpy, bit for
    bit, in float64 and float32; and e agrees with |y| - |xi| to the cancellation's rounding."""
    p, bonds = plate(dim)
    u = np.random.default_rng(dim).normal(scale=0.05, size=(p.n, dim)).astype(dtype)
    ends, xi, length = geometry(bonds, torch.float64 if dtype == np.float64 else torch.float32)
    s = bond_loops.stretch(torch.as_tensor(u), ends, xi, length).numpy()
    y, r, e, _ = numpy_bond(u, bonds, dtype)
    assert s.dtype == dtype
    np.testing.assert_array_equal(s, e / bonds.length.astype(dtype))
    if dtype == np.float64:
        np.testing.assert_allclose(e, r - bonds.length, rtol=0, atol=16 * np.finfo(dtype).eps)


@pytest.mark.parametrize("dim", [2, 3])
def test_pmb_force_is_the_bond_sum_bit_for_bit_and_conserves_momentum(dim):
    """f_i += t y, f_j -= the same, t = k mu e / |y| taken as k mu num / ((|y| + |xi|) |y|)
    (num = eta . (y + xi), one division), bond by bond in order: equal bit for bit to that
    sum done in Python floats (the same IEEE operations), and to the two-division
    k mu (num / (|y| + |xi|)) / |y| to (4 + n) eps sum |terms| for an entry of n terms (three
    roundings of t either way and one of its product with y: 4 eps a term; each sum's n - 1
    additions: (n - 1) eps/2 sum |terms| each); sum_i f_i = 0 (Newton's
    third law, to rounding); a broken bond (k mu = 0) adds exactly nothing; mu = None is mu = 1."""
    p, bonds = plate(dim)
    rng = np.random.default_rng(10 + dim)
    u = rng.normal(scale=0.05, size=(p.n, dim))
    k = rng.uniform(1.0, 2.0, bonds.n)
    mu = rng.uniform(0.0, 1.0, bonds.n)
    mu[::5] = 0.0
    ends, xi, length = geometry(bonds)
    f = bond_loops.pmb_force(torch.as_tensor(u), ends, xi, length, torch.as_tensor(k), torch.as_tensor(mu)).numpy()
    y, r, e, num = numpy_bond(u, bonds)
    ref, two = np.zeros_like(u), np.zeros_like(u)
    size, count = np.zeros_like(u), np.zeros_like(u)  # sum of |terms| and their number per entry
    for b in range(bonds.n):
        kb = float(k[b] * mu[b])
        if kb == 0.0:
            continue
        t, t2 = kb * float(num[b]) / ((float(r[b]) + float(bonds.length[b])) * float(r[b])), kb * float(e[b]) / float(r[b])
        for a in range(dim):
            fb = float(y[b, a]) * t
            ref[bonds.i[b], a] += fb
            ref[bonds.j[b], a] -= fb
            two[bonds.i[b], a] += float(y[b, a]) * t2
            two[bonds.j[b], a] -= float(y[b, a]) * t2
            for end in (bonds.i[b], bonds.j[b]):
                size[end, a] += abs(fb)
                count[end, a] += 1
    np.testing.assert_array_equal(f, ref)
    assert np.all(np.abs(f - two) <= (4 + count) * np.finfo(float).eps * size)
    np.testing.assert_allclose(f.sum(0), 0.0, atol=64 * np.finfo(float).eps * np.abs(f).max())
    intact = bond_loops.pmb_force(torch.as_tensor(u), ends, xi, length, torch.as_tensor(k), None)
    ones = bond_loops.pmb_force(torch.as_tensor(u), ends, xi, length, torch.as_tensor(k), torch.ones(bonds.n))
    assert torch.equal(intact, ones)


def test_tangent_is_the_derivative_of_the_force():
    """In tension (every bond stretched, c = 1 - |xi| / |y| > 0) the PMB tangent
    k [c I + (1 - c) n n^T] is the exact Hessian of the bond energy: tangent_change with
    before = 0, after = mu gives T(u) with T v = -(f(u + h v) - f(u - h v)) / (2 h) + O(h^2)
    (measured: the remainder falls by 4 when h halves); a zero change (same u, same mu)
    emits entries that cancel exactly; dofs marked -1 in ``local`` are left out."""
    p, bonds = plate(2)
    rng = np.random.default_rng(4)
    u = 0.01 * p.x + rng.normal(scale=1e-3, size=p.x.shape)  # 1 % expansion: all bonds in tension
    k = rng.uniform(1.0, 2.0, bonds.n)
    mu = rng.uniform(0.5, 1.0, bonds.n)
    ends, xi, length = geometry(bonds)
    n_dof = 2 * p.n
    local = np.arange(n_dof)
    every = np.arange(bonds.n)
    rows, cols, vals = bond_loops.tangent_change(u, u, ends, xi.numpy(), length.numpy(), k, every,
                                                 np.zeros(bonds.n), mu, local)
    T = sp.coo_matrix((vals, (rows, cols)), shape=(n_dof, n_dof)).toarray()
    np.testing.assert_allclose(T, T.T, rtol=0, atol=1e-13 * np.abs(T).max())

    def force(v):
        return bond_loops.pmb_force(torch.as_tensor(v), ends, xi, length, torch.as_tensor(k),
                                    torch.as_tensor(mu)).numpy().reshape(-1)

    v = rng.standard_normal(p.x.shape)
    rem = [np.linalg.norm(T @ v.reshape(-1) + (force(u + h * v) - force(u - h * v)) / (2 * h)) for h in (1e-3, 5e-4)]
    assert np.log2(rem[0] / rem[1]) == pytest.approx(2.0, abs=0.1)
    _, _, zero = bond_loops.tangent_change(u, u, ends, xi.numpy(), length.numpy(), k, every, mu, mu, local)
    assert len(zero) == len(vals) and np.all(zero == 0.0)
    drop = local.copy()
    drop[:4] = -1  # the first two particles' dofs left out
    r2, c2, _ = bond_loops.tangent_change(u, u, ends, xi.numpy(), length.numpy(), k, every, np.zeros(bonds.n), mu, drop)
    assert r2.min() >= 0 and c2.min() >= 0 and len(r2) == int(np.sum((rows >= 4) & (cols >= 4)))


def test_damage_sums_are_the_torch_index_adds_bit_for_bit(monkeypatch):
    """The damage index phi_i = sum_j w (1 - mu) V_j / sum_j w V_j: compiled and torch
    (ENABLED = False) paths give the same bits, on unequal volumes and partial damage."""
    rng = np.random.default_rng(2)
    g = bp.grid_2d(8.0, 6.0, 1.0)
    p = bp.from_points(g.x, rng.uniform(0.5, 1.5, g.n))
    bonds = bp.find_bonds(p, 2.5)
    mu = torch.as_tensor(np.where(rng.random(bonds.n) < 0.3, rng.random(bonds.n), 1.0))
    index = DamageIndex(p, bonds, weight=bonds.weight(2.5))
    phi = {}
    for enabled in (True, False):
        monkeypatch.setattr(bond_loops, "ENABLED", enabled)
        assert bond_loops.usable(mu) == enabled
        phi[enabled] = index(mu)
    assert torch.equal(phi[True], phi[False]) and float(phi[True].max()) > 0
    w, V = index.w, index.V
    direct = bond_loops.damage_sums(index.i, index.j, w, mu, V)
    damaged = mu < 1
    torch_sums = torch.zeros(p.n).index_add(0, index.i[damaged], (w * (1 - mu))[damaged] * V[index.j[damaged]]) \
        .index_add(0, index.j[damaged], (w * (1 - mu))[damaged] * V[index.i[damaged]])
    assert torch.equal(direct, torch_sums)


def test_tally_is_the_torch_expression_bit_for_bit():
    """(max |intact - operated|, intact < 1/2, its count, whether it differs from ``broken``)."""
    rng = np.random.default_rng(3)
    intact = torch.as_tensor(rng.random(500))
    operated = torch.as_tensor(np.clip(intact.numpy() + rng.normal(scale=0.1, size=500), 0, 1))
    for broken in (intact < 0.5, operated < 0.5):
        moved, now, count, differs = bond_loops.tally(intact, operated, broken)
        assert moved == float((intact - operated).abs().max())
        assert torch.equal(now, intact < 0.5) and count == int((intact < 0.5).sum())
        assert differs == (not torch.equal(intact < 0.5, broken))


def test_usable_only_for_cpu_tensors_of_one_float_dtype_without_grad(monkeypatch):
    x64, x32 = torch.zeros(3), torch.zeros(3, dtype=torch.float32)
    assert bond_loops.usable() and bond_loops.usable(x64, None) and bond_loops.usable(x32)
    assert not bond_loops.usable(x64, x32) and not bond_loops.usable(torch.zeros(3, dtype=torch.int64))
    assert not bond_loops.usable(x64.clone().requires_grad_())
    with torch.no_grad():
        assert bond_loops.usable(x64.clone().requires_grad_())
    monkeypatch.setattr(bond_loops, "ENABLED", False)
    assert not bond_loops.usable() and not bond_loops.usable(x64)


@pytest.mark.parametrize("compiled", [True, False])
def test_components_number_the_pieces_as_scipy_does(monkeypatch, compiled):
    """``bond_loops.components`` (union-find, or scipy without numba) gives scipy's count and
    labels exactly, on 300 random graphs (self-loops, repeated edges, isolated vertices,
    edges left out by ``keep``; every other one sorted by first end, as bonds are) and on
    the 10k-particle plate's bonds cut along a line; the union-find runs when it should."""
    monkeypatch.setattr(bond_loops, "ENABLED", compiled)
    calls, union_find = [], bond_loops._components
    monkeypatch.setattr(bond_loops, "_components", lambda *a: calls.append(1) or union_find(*a))
    rng = np.random.default_rng(0)

    def scipy_components(n, i, j, keep):
        graph = sp.coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(n, n))
        return connected_components(graph, directed=False)

    for _ in range(300):
        n, m = int(rng.integers(1, 60)), int(rng.integers(0, 90))
        i, j, keep = rng.integers(0, n, m), rng.integers(0, n, m), rng.random(m) < 0.8
        if _ % 2:
            order = np.argsort(i, kind="stable")
            i, j = i[order], j[order]
        count, labels = bond_loops.components(n, i, j, keep)
        expected = scipy_components(n, i, j, keep)
        assert count == expected[0] and np.array_equal(labels, expected[1])
    p = bp.grid_2d(100.0, 100.0, 1.0)
    bonds = bp.find_bonds(p, 3.0)
    keep = ~((np.minimum(p.x[bonds.i, 1], p.x[bonds.j, 1]) < 50) & (np.maximum(p.x[bonds.i, 1], p.x[bonds.j, 1]) > 50))
    count, labels = bond_loops.components(p.n, bonds.i, bonds.j, keep)
    assert count == 2 and np.array_equal(labels, scipy_components(p.n, bonds.i, bonds.j, keep)[1])
    assert len(calls) == (301 if compiled and bond_loops.numba is not None else 0)


@pytest.fixture
def threads():
    """Sets torch's thread count for a test, restoring it afterwards."""
    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)


@pytest.mark.parametrize("per_thread", [1, 3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("dim", [2, 3])
def test_pmb_force_on_threads_is_the_one_thread_sum(dim, dtype, per_thread, threads, monkeypatch):
    """Over 3 threads (1 or 3 shares each) each share sums its bonds in order into rows of its
    own, added up in share order: a particle that one share touches gets the one-thread force
    bit for bit, one touched by two the same terms in another association (a few ulp of the
    largest force); float32 agrees with the float64 force to 64 float32 ulp. The shares are
    consecutive runs of bonds covering all of them, and each one's rows hold its particles."""
    p = bp.grid_2d(30.0, 20.0, 1.0) if dim == 2 else bp.grid_3d(6.0, 16.0, 6.0, 1.0)
    bonds = bp.find_bonds(p, 2.0)
    rng = np.random.default_rng(dim)
    u = torch.as_tensor(rng.normal(scale=0.05, size=(p.n, dim)), dtype=dtype)
    k, mu = torch.as_tensor(rng.uniform(1.0, 2.0, bonds.n), dtype=dtype), torch.as_tensor(rng.uniform(0.0, 1.0, bonds.n), dtype=dtype)
    ends, xi, length = geometry(bonds, dtype)
    monkeypatch.setattr(bond_loops, "MIN_SHARE", bonds.n // 12)
    monkeypatch.setattr(bond_loops, "SHARES_PER_THREAD", per_thread)
    threads(1)
    serial = bond_loops.pmb_force(u, ends, xi, length, k, mu)
    threads(3)
    on_threads = bond_loops.pmb_force(u, ends, xi, length, k, mu)
    parts = bond_loops.shares(ends, 3 * per_thread)
    assert len(parts) == 3 * per_thread and parts[0][0] == 0 and parts[-1][1] == bonds.n
    touches = np.zeros(p.n, dtype=int)
    for t, (b0, b1, lo, hi) in enumerate(parts):
        assert t == 0 or b0 == parts[t - 1][1]
        touched = np.union1d(bonds.i[b0:b1], bonds.j[b0:b1])
        assert touched.min() == lo and touched.max() == hi - 1
        touches[lo:hi] += 1
    assert touches.min() >= 1 and touches.max() > 1 and (per_thread > 1 or (touches == 1).sum() > p.n / 4)
    eps = torch.finfo(dtype).eps
    assert torch.equal(on_threads[touches == 1], serial[touches == 1])
    assert float((on_threads - serial).abs().max()) <= 8 * eps * float(serial.abs().max())
    if dtype == torch.float32:
        exact = bond_loops.pmb_force(u.double(), ends, xi.double(), length.double(), k.double(), mu.double())
        assert float((on_threads - exact).abs().max()) <= 64 * eps * float(exact.abs().max())


def test_a_share_that_no_thread_finished_is_done_by_the_caller(threads, monkeypatch):
    """A pool thread that never runs its claim (here: it is handed a kernel that fails) delays
    nothing and loses nothing: the caller does those shares again and the force is the
    one-thread force to rounding; bonds in any order (here reversed, so each share's
    particle range is wide) give the same force."""
    p, bonds = plate()
    monkeypatch.setattr(bond_loops, "MIN_SHARE", 8)
    ends, xi, length = geometry(bonds)
    u = torch.as_tensor(np.random.default_rng(4).normal(scale=0.05, size=(p.n, 2)))
    k = torch.ones(bonds.n, dtype=torch.float64)
    threads(1)
    serial = bond_loops.pmb_force(u, ends, xi, length, k, None)
    caller = threading.get_ident()

    def only_on_the_caller(*args):
        if threading.get_ident() != caller:
            raise RuntimeError("a pool thread set aside")
        bond_loops._pmb_force(*args)

    args = (bond_loops._BOND[2], u.numpy(), *ends, xi.numpy(), length.numpy(), k.numpy(), np.ones(1), False)
    f = bond_loops.shared(only_on_the_caller, args, bond_loops.shares(ends, 6), u.shape, np.float64, 3)
    np.testing.assert_allclose(f, serial.numpy(), rtol=0, atol=8 * np.finfo(float).eps * float(serial.abs().max()))
    reverse = tuple(e[::-1].copy() for e in ends)
    threads(2)
    f = bond_loops.pmb_force(u, reverse, xi.flip(1).contiguous(), length.flip(0).contiguous(), k, None)
    assert len(bond_loops.shares(reverse, 16)) == 16
    np.testing.assert_allclose(f.numpy(), serial.numpy(), rtol=0, atol=8 * np.finfo(float).eps * float(serial.abs().max()))


@pytest.mark.parametrize("redo", [True, False])
def test_claimed_redoes_a_stalled_task_or_waits_for_it(redo):
    """A task that stalls on a pool thread (0.3 s; the caller's first task waits until the pool
    thread holds one) is done again by the caller (``redo``: run twice) or waited for (each
    task run exactly once, all finished at return)."""
    import time

    runs, finished, lock, pool_busy = [0] * 4, [False] * 4, threading.Lock(), threading.Event()

    def task(t):
        with lock:
            runs[t] += 1
            first = runs[t] == 1
        if threading.current_thread() is threading.main_thread():
            assert pool_busy.wait(5.0), "the pool thread never claimed a task"
        elif first:
            pool_busy.set()
            time.sleep(0.3)
        finished[t] = True
        return t * t

    assert bond_loops.claimed(task, 4, 2, redo=redo) == [0, 1, 4, 9]
    if redo:
        assert sum(runs) == 5  # the stalled task run again by the caller
        time.sleep(0.4)  # let the late run end before the next test
    else:
        assert runs == [1, 1, 1, 1] and all(finished)
