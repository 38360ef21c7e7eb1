"""How the ranks of a slab decomposition (rockwave/sim/distributed.py) move particle buffers to their neighbours.

A transport exchanges contiguous Warp arrays (float32 rows packed by kernels/sim/distributed.py) with the lower
and upper neighbour ranks; both sides know every message's length beforehand (the counts are agreed over MPI at
each list rebuild), so an exchange is one send and one receive per neighbour. Three kinds:

* ``nccl``: GPU to GPU through NCCL point-to-point (ncclSend/ncclRecv in one group), stream-ordered on the Warp
  stream of the rank's device, no host copy and no host wait. The NCCL unique id is made on rank 0 and broadcast
  with mpi4py (the pattern of NCCL's own MPI examples). Bindings: ``nccl4py`` (``nccl.core``) or CuPy's
  ``cupy.cuda.nccl``, whichever imports. One rank per GPU (NCCL refuses two ranks on one device).
* ``cuda-mpi``: mpi4py with the device arrays themselves as buffers (their ``__cuda_array_interface__``), for an
  MPI built CUDA-aware; the Warp stream is synchronized before the messages are posted.
* ``host``: mpi4py on host copies (on the CPU the host arrays themselves, no copy): the CPU path (CI) and the
  fallback.

``make_transport("auto", ...)`` takes nccl on a CUDA device when a binding imports, else cuda-mpi when the MPI says
it is CUDA-aware, else host.
"""

from __future__ import annotations

import os

import numpy as np
import warp as wp

KINDS = ("auto", "nccl", "cuda-mpi", "host")


def _mpi():
    from mpi4py import MPI

    return MPI


class HostTransport:
    """mpi4py on host buffers: device arrays are copied to the host and back (numpy views on the CPU)."""

    name = "host"

    def __init__(self, comm, device):
        self.comm = comm
        self.device = wp.get_device(device)

    def exchange(self, pairs) -> None:
        """``pairs``: (peer, send, recv) per neighbour, peer None for none; send/recv Warp arrays whose sizes both
        sides agreed. Sends send to peer and fills recv with what peer sent."""
        MPI = _mpi()
        reqs, back = [], []
        for peer, send, recv in pairs:
            if peer is None:
                continue
            if recv is not None and recv.size:
                host = recv.numpy() if not self.device.is_cuda else np.empty(recv.shape, dtype=wp.dtype_to_numpy(recv.dtype))
                reqs.append(self.comm.Irecv(host, source=peer, tag=17))
                if self.device.is_cuda:
                    back.append((recv, host))
            if send is not None and send.size:
                reqs.append(self.comm.Isend(np.ascontiguousarray(send.numpy()), dest=peer, tag=17))
        MPI.Request.Waitall(reqs)
        for recv, host in back:
            recv.assign(host)


class CudaMPITransport(HostTransport):
    """A CUDA-aware MPI reading and writing the device arrays directly."""

    name = "cuda-mpi"

    def exchange(self, pairs) -> None:
        MPI = _mpi()
        wp.synchronize_stream(wp.get_stream(self.device))  # the packing kernels are done
        reqs = []
        for peer, send, recv in pairs:
            if peer is None:
                continue
            if recv is not None and recv.size:
                reqs.append(self.comm.Irecv([recv, MPI.FLOAT if recv.dtype == wp.float32 else MPI.INT], source=peer, tag=18))
            if send is not None and send.size:
                reqs.append(self.comm.Isend([send, MPI.FLOAT if send.dtype == wp.float32 else MPI.INT], dest=peer, tag=18))
        MPI.Request.Waitall(reqs)


def cuda_aware_mpi() -> bool:
    """Does the MPI library say it is CUDA-aware? (MPIX_Query_cuda_support through mpi4py when it has it; Open MPI's
    OMPI_MCA_opal_cuda_support; ROCKWAVE_CUDA_AWARE_MPI=1 forces it.)"""
    if os.environ.get("ROCKWAVE_CUDA_AWARE_MPI") == "1":
        return True
    MPI = _mpi()
    q = getattr(MPI, "Query_cuda_support", None)
    if q is not None:
        try:
            return bool(q())
        except Exception:  # noqa: BLE001 - not every MPI implements the extension
            return False
    return os.environ.get("OMPI_MCA_opal_cuda_support", "").lower() in ("1", "true")


class NcclTransport:
    """NCCL point-to-point on the rank's Warp stream (module doc)."""

    name = "nccl"

    def __init__(self, comm, device):
        self.comm = comm
        self.device = wp.get_device(device)
        if not self.device.is_cuda:
            raise RuntimeError("the nccl transport needs a CUDA device")
        self.binding, self._nccl = self._import()
        rank, size = comm.Get_rank(), comm.Get_size()
        if self.binding == "nccl4py":
            uid = self._nccl.get_unique_id() if rank == 0 else None
            uid = comm.bcast(uid, root=0)
            comm.Barrier()
            self.nccl = self._nccl.Communicator.init(nranks=size, rank=rank, unique_id=uid)
        else:
            import cupy

            cupy.cuda.Device(self.device.ordinal).use()
            uid = self._nccl.get_unique_id() if rank == 0 else None
            uid = comm.bcast(uid, root=0)
            comm.Barrier()
            self.nccl = self._nccl.NcclCommunicator(size, uid, rank)

    @staticmethod
    def _import():
        try:
            import nccl.core as nccl

            return "nccl4py", nccl
        except ImportError:
            pass
        from cupy.cuda import nccl  # ImportError when neither binding is there

        if not getattr(nccl, "available", True):  # CuPy without its NCCL library
            raise ImportError("cupy.cuda.nccl: CuPy found no NCCL library")
        return "cupy", nccl

    def exchange(self, pairs) -> None:
        stream = wp.get_stream(self.device)
        if self.binding == "nccl4py":
            with self._nccl.group():
                for peer, send, recv in pairs:
                    if peer is None:
                        continue
                    if send is not None and send.size:
                        self.nccl.send(send, peer, stream=stream)
                    if recv is not None and recv.size:
                        self.nccl.recv(recv, peer, stream=stream)
            return
        n = self._nccl
        s = stream.cuda_stream
        n.groupStart()
        try:
            for peer, send, recv in pairs:
                if peer is None:
                    continue
                if send is not None and send.size:
                    self.nccl.send(send.ptr, send.size, _nccl_type(n, send), peer, s)
                if recv is not None and recv.size:
                    self.nccl.recv(recv.ptr, recv.size, _nccl_type(n, recv), peer, s)
        finally:
            n.groupEnd()


def _nccl_type(n, a):
    return n.NCCL_FLOAT32 if a.dtype == wp.float32 else n.NCCL_INT32


def make_transport(kind: str, comm, device):
    """The transport ``kind`` (KINDS) for ``device``; "auto": nccl on CUDA when a binding imports, else cuda-mpi
    when the MPI is CUDA-aware, else host. An explicit kind that cannot run raises ValueError naming why."""
    if kind not in KINDS:
        raise ValueError(f"transport {kind!r}: expected one of {', '.join(KINDS)}")
    dev = wp.get_device(device)
    if kind == "host" or (kind == "auto" and not dev.is_cuda):
        return HostTransport(comm, dev)
    if kind in ("nccl", "auto") and dev.is_cuda:
        try:
            NcclTransport._import()
            here = 1
        except ImportError:
            here = 0
        # every rank takes the same kind (the NCCL set-up is collective)
        if comm.allreduce(here, op=_mpi().MIN):
            return NcclTransport(comm, dev)
        if kind == "nccl":
            raise ValueError("transport nccl: no NCCL binding imports on every rank (pip install nccl4py, or cupy "
                               "with NCCL)")
    if not dev.is_cuda:
        raise ValueError(f"transport {kind}: needs a CUDA device, the ranks run on {dev}")
    if kind == "cuda-mpi" or cuda_aware_mpi():
        return CudaMPITransport(comm, dev)
    return HostTransport(comm, dev)
