"""Posterior-predictive crack ensembles: a ``FractureScene`` (``scene``) realised at posterior
draws (``predictive.ensemble``), locally or on Dask (``execution``), stored resumably
(``store``) and aggregated (``stats``)."""
