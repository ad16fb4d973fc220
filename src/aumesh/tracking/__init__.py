"""MLflow tracking: the store, cleaned params, runs and their helper process, queries, the registry, the pyfunc
wrapper and the local server. The only package that imports ``mlflow``."""
