"""dfxcorr: maximum-likelihood correction of grating vibrations in scanning Talbot-Lau X-ray interferometers.

The stages are modules (``io``, ``align``, ``mask``, ``fit``, ``retrieve``, ``export``) over one forward
model (``model``); :func:`dfxcorr.pipeline.reconstruct` chains them.
"""
__version__ = "0.1.0"
